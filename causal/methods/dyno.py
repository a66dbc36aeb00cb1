"""Dyn-O (dissertation ch. 7) as a Causeway method: object slots from frames (eq. 7.1, the annealed
mask prior) and a slot world model (eq. 7.2), trained by the dynamics-learner on ``chemical-pixels`` (or on
``chemical-pixels-two-tone``, objects of two parts: the env sets ``two_tone``).

The parts live in :mod:`causal.dyno` (the model, the phased trainer, the FG-ARI scorer),
:mod:`causal.slots` and :mod:`causal.slot_world_model`; this module names them for the registry. Dyn-O
estimates no graph over the given factors (no graph-evaluator runs); a run's summary carries its
``slots`` block (FG-ARI of the final model's slots without masks).
"""
from __future__ import annotations

from causal.dyno import DynOConfig, DynOTrainer, SlotScores, model_from_config
from causal.method import Method

METHOD = Method(
    name="dyno",
    title="Dyn-O (ch. 7): object slots from rendered frames (annealed mask prior) and a slot world model",
    config=DynOConfig,
    trainer=lambda layout, cfg, seed: DynOTrainer(layout, cfg, seed),
    model_from_config=model_from_config,
    slots=SlotScores(),
    envs=("chemical-pixels", "chemical-pixels-two-tone"),
    env_settings={"chemical-pixels-two-tone": {"two_tone": True}},
)
