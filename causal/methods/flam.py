"""FLAM (dissertation ch. 8) as a Causeway method: the FSQ autoencoder (eq. 8.1) and the factored latent
action model (eqs. 8.2-8.6), trained by the dynamics-learner on ``multigrid-agents`` (or its correlated
variant) from frames of the run's transitions, without their actions.

The parts live in :mod:`causal.flam_learner` (the model, the phased trainer, the scorer) and
:mod:`causal.flam`; this module names them for the registry. FLAM estimates no graph over the given
factors (no graph-evaluator runs); a run's summary carries its ``latent_actions`` block (10-step PSNR
and DCI of the final model's latent actions on unseen videos).
"""
from __future__ import annotations

from causal.flam_learner import FLAMRunConfig, FLAMTrainer, LatentActionScores, check_layout, model_from_config
from causal.method import Method

METHOD = Method(
    name="flam",
    title="FLAM (ch. 8): per-slot latent actions learned from frames (FSQ autoencoder, factorizer, IDM/FDM)",
    config=FLAMRunConfig,
    trainer=lambda layout, cfg, seed: FLAMTrainer(layout, cfg, seed),
    model_from_config=model_from_config,
    latent_actions=LatentActionScores(),
    envs=("multigrid-agents", "multigrid-agents-correlated"),
    check_layout=check_layout,
    resumable=("lr_decay_updates", "lr_final", "clip_frames"),
)
