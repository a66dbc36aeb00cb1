"""Table 4.1 and Figs. 4.5-4.6 on Chemical with distractors, the block scene or the tool-use scene:
implicit vs explicit CBM from the same data.

For each seed: random-policy transitions of ``chemical-distractors``, ``block`` or ``tool-use``
(``--env``; on block every other episode starts with a scripted grasp of ``mov1``, on tool-use with
part of the scripted Series solution, so that contacts occur; 10% of episodes held out), then
CBM with implicit dynamics and CBM with explicit (CDL's) dynamics trained on the same data for the same
number of updates. As the graph-evaluator does live, the dynamics CMI (eq. 4.3 / eq. 3.2) and the
reward CMI are estimated on the held-out data every ``--estimate-every`` updates and averaged over
training (0.999 per update), and the causal term's parents come from the averaged graph. From the
averages: the dynamics graph, the reward's parents (reward CMI >= 0.01) and the minimal abstraction
(Theorem 4.1), scored against the env's truth:

* graph ``accuracy`` over every off-diagonal entry and ``with_self_accuracy`` over every entry (Table
  4.1 counts every entry, so true negatives dominate: ``empty_accuracy`` is what a graph without a
  single edge scores), ``f1``, and ``non_distractor_f1``: F1 over the entries whose cause and effect are
  not distractors;
* reward parents: accuracy and F1 of the learned parent vector (factors and action);
* abstraction accuracy (share of state factors kept or dropped as the true minimal abstraction does)
  with the learned reward parents, with the true ones (Table 4.1's setting), and of CDL's
  task-independent abstraction of the same learned graph.

Writes ``<out>/cbm_table.json``, a markdown table to stdout and ``<out>/cbm_abstractions_s<seed>.png``
(which factors each abstraction keeps; Figs. 4.5-4.6).

``--fdr Q`` also decides the trained model's graph by issue 22's FDR rule instead of the fixed
threshold: one CMI estimate of the final model on every held-out transition with its standard errors
(eq. 4.3's per-sample terms; CDL's log-likelihood ratios for the explicit variant), and an edge where
the test of ``CMI > --fdr-min-cmi`` (default: the 0.02-nat threshold itself) rejects at
false-discovery rate Q (Benjamini-Hochberg over the off-diagonal entries). An edge then has to be
shown above the threshold, not just estimated above it. Reported under ``fdr``: the graph's scores,
its abstractions (with the learned reward parents of the averaged reward CMI, as above) and its edge
count beside the fixed threshold's on the same estimate. Not the chapter's rule (a deviation to test
whether estimates barely over 0.02 nats are what breaks the abstraction).

``--reward-only`` trains the causal reward model alone (it does not need the dynamics) on the same
data, batches and schedule of estimates, and writes ``<out>/cbm_reward.json`` and a table: the reward
data (share of non-zero rewards, distinct values), the reward CMI per input averaged over training,
the reward parents' F1, the abstraction from the learned reward parents through the env's *true*
dynamics graph, and, from the same trained model, the parents the per-mask-variance CMI
``0.5 log(MSE_{-i} / MSE)`` used before issue 19 would give (a before/after on identical predictions).

    python -m benchmarks.cbm_graph_table --num-objects 3 --distractors 5,5 --updates 5000 --seeds 0 1 2
    python -m benchmarks.cbm_graph_table --env block --task pick --distractors 20,20 --steps 5000 --updates 1000
    python -m benchmarks.cbm_graph_table --env tool-use --task series --distractors 20,20 --steps 5000 --updates 1000
    python -m benchmarks.cbm_graph_table --num-objects 3 --distractors 5,5 --task match-first --reward-only --seeds 0 1 2
    python -m benchmarks.cbm_graph_table --merge run0/cbm_table.json run1/cbm_table.json --out merged
"""
from __future__ import annotations

import argparse
import sys
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from causal.abstraction import abstraction_accuracy, cdl_abstraction, minimal_abstraction, with_self_edges
from causal.cbm import CBMTrainer
from causal.cbm_config import TARGETS, CBMConfig
from causal.cbm_reward import CausalRewardModel
from causal.edge_tests import EdgeEstimate, decide
from causal.factored import FactorLayout
from causal.graph_metrics import binary_scores, score_graph, scored_entries
from causal.methods.cbm import DynamicsCMI
from envs.distractors import is_distractor
from envs.registry import make_env
from proto.messages import EnvSpec


BLOCK_CUBES = ("mov1", "mov2", "mov3")


class CollectionPolicy:
    """Uniformly random actions; on ``block``, every other episode opens with a scripted grasp of
    ``mov1`` (or, with ``grasp_targets``, of one of those cubes drawn uniformly per episode), on
    ``tool-use`` with the scripted Series solution (:class:`envs.tool_use.SeriesScript`) cut off after a
    uniformly random 10-160 steps (random actions would rarely touch a cube, and never use the tool)."""

    def __init__(self, env: Any, env_name: str, seed: int, grasp_targets: tuple[str, ...] = ("mov1",)) -> None:
        if not grasp_targets or not set(grasp_targets) <= set(BLOCK_CUBES):
            raise ValueError(f"grasp_targets must be some of {BLOCK_CUBES}, got {grasp_targets!r}")
        self.env, self.env_name, self.grasp_targets = env, env_name, tuple(grasp_targets)
        self.rng, self.skill, self.episode, self.budget = np.random.default_rng(seed), None, 0, 0

    def start_episode(self) -> None:
        from envs.manipulation_layout import BLOCK
        from envs.skills import grasp
        from envs.tool_use import SeriesScript

        scripted = self.episode % 2 == 0
        self.episode += 1
        self.skill = None
        if scripted and self.env_name == "block":  # one target draws nothing: the default's stream stays as it was
            target = self.grasp_targets[0] if len(self.grasp_targets) == 1 else str(self.rng.choice(self.grasp_targets))
            self.skill = grasp(target, layout=BLOCK)
        elif scripted and self.env_name == "tool-use":  # the budget is drawn only here: other envs' draws stay as they were
            self.skill, self.budget = SeriesScript(), int(self.rng.integers(10, 161))

    def act(self, obs: np.ndarray) -> np.ndarray | int:
        if self.skill is not None and self.env_name == "tool-use":
            self.budget -= 1
            if self.budget < 0:
                self.skill = None
        action = None if self.skill is None else self.skill.act(obs)
        if action is not None:
            return action
        space = self.env.action_space
        if isinstance(space, gym.spaces.Discrete):
            return int(self.rng.integers(space.n))
        return self.rng.uniform(space.low, space.high).astype(np.float32)


def collect(env_kwargs: dict[str, Any], steps: int, seed: int, env_name: str = "chemical-distractors",
            grasp_targets: tuple[str, ...] = ("mov1",)) -> tuple[EnvSpec, dict[str, np.ndarray]]:
    """``steps`` collection-policy transitions of ``env_name``; ``heldout`` marks every tenth episode,
    ``first`` each episode's first step."""
    env = make_env(env_name, **env_kwargs).unwrapped
    policy = CollectionPolicy(env, env_name, seed, grasp_targets)
    obs, _ = env.reset(seed=seed)
    policy.start_episode()
    rows: dict[str, list] = {k: [] for k in ("state", "action", "next_state", "reward", "heldout", "first")}
    episode, first = 0, True
    for step in range(1, steps + 1):
        if step % 2000 == 0:
            print(f"  collected {step}/{steps} steps of {env_name}", file=sys.stderr, flush=True)
        action = policy.act(obs)
        nxt, reward, terminated, truncated, _ = env.step(action)
        for key, value in zip(rows, (obs, np.atleast_1d(action), nxt, reward, episode % 10 == 9, first)):
            rows[key].append(value)
        obs, first = nxt, False
        if terminated or truncated:
            obs, episode, first = env.reset()[0], episode + 1, True
            policy.start_episode()
    spec = env.env_spec()
    env.close()
    return spec, {k: np.asarray(v, dtype=bool if k in ("heldout", "first") else np.float32) for k, v in rows.items()}


def tensors(data: dict[str, np.ndarray], rows: np.ndarray) -> tuple[torch.Tensor, ...]:
    return tuple(torch.from_numpy(data[k][rows]) for k in ("state", "action", "next_state", "reward"))


@dataclass
class Trained:
    """A trained model, the moving averages of its CMI estimates over training, seconds per update."""

    trainer: CBMTrainer
    cmi: np.ndarray
    reward_cmi: np.ndarray
    seconds_per_update: float


def train(spec: EnvSpec, cfg: CBMConfig, data: dict[str, np.ndarray], updates: int, estimate_every: int,
          ema: float, seed: int) -> Trained:
    """``updates`` CBM updates on the training rows. Every ``estimate_every`` updates, as the
    graph-evaluator does live: the dynamics CMI (the model's own estimator and defaults) and the reward
    CMI on the held-out rows, averaged with weight ``ema ** estimate_every`` on the previous average,
    the causal term's parents taken from the averaged graph."""
    trainer = CBMTrainer(FactorLayout.from_spec(spec), cfg, seed=seed)
    train_rows, held = np.flatnonzero(~data["heldout"]), tensors(data, np.flatnonzero(data["heldout"]))
    rng, generator = np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    seconds, cmi, reward_cmi = 0.0, None, None
    weight = ema ** estimate_every
    for u in range(1, updates + 1):
        batch = tensors(data, rng.choice(train_rows, cfg.batch_size))
        started = time.perf_counter()
        trainer.update(*batch)
        seconds += time.perf_counter() - started
        if u % estimate_every == 0 or u == updates:
            new = trainer.model.dynamics_cmi(*held[:3], generator).numpy()
            new_reward = trainer.model.reward_cmi(held[0], held[1], held[3]).numpy()
            cmi = new if cmi is None else weight * cmi + (1 - weight) * new
            reward_cmi = new_reward if reward_cmi is None else weight * reward_cmi + (1 - weight) * new_reward
            trainer.set_parents(cmi >= cfg.cmi_threshold)
            print(f"  {cfg.dynamics} update {u}/{updates}: {seconds / u:.3f} s an update, "
                  f"{int((cmi >= cfg.cmi_threshold).sum())} dynamics edges", file=sys.stderr, flush=True)
    return Trained(trainer, cmi, reward_cmi, seconds / max(updates, 1))


@dataclass
class TrainedReward:
    """A reward model trained alone, its reward CMI averaged over training (the model's estimator and the
    per-mask-variance one used before issue 19, from the same predictions), and every estimate."""

    model: CausalRewardModel
    reward_cmi: np.ndarray
    per_mask_cmi: np.ndarray
    trace: list[dict[str, Any]]
    seconds_per_update: float


def per_mask_variance_cmi(model: CausalRewardModel, state: torch.Tensor, action: torch.Tensor,
                          reward: torch.Tensor) -> np.ndarray:
    """The reward CMI with one maximum-likelihood variance per mask, ``0.5 log(MSE_{-i} / MSE)``: the
    estimator before issue 19, kept here only to compare (constant inputs 0, as the model's)."""
    with torch.no_grad():
        mse = model.squared_errors(state, action, reward).double().mean(dim=1)
    cmi = (0.5 * torch.log(mse[1:] / mse[:1].clamp_min(1e-12))).numpy()
    cmi[model.cmi(state, action, reward).numpy() == 0] = 0.0  # constant inputs (and a constant reward)
    return cmi


def train_reward(spec: EnvSpec, cfg: CBMConfig, data: dict[str, np.ndarray], updates: int, estimate_every: int,
                 ema: float, seed: int) -> TrainedReward:
    """``updates`` Adam steps on the reward model alone (its loss in :meth:`CBMTrainer.update`: squared
    error under the full and every drop-one mask, the same clip), on the batches :func:`train` draws;
    the reward CMI on the held-out rows every ``estimate_every`` updates, averaged as there."""
    torch.manual_seed(seed)
    layout = FactorLayout.from_spec(spec)
    model = CausalRewardModel(layout, cfg)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    train_rows, held = np.flatnonzero(~data["heldout"]), tensors(data, np.flatnonzero(data["heldout"]))
    rng, weight = np.random.default_rng(seed), ema ** estimate_every
    truth = np.asarray(spec.reward_parents, bool)
    seconds, cmi, per_mask, trace = 0.0, None, None, []
    for u in range(1, updates + 1):
        state, action, _, reward = tensors(data, rng.choice(train_rows, cfg.batch_size))
        started = time.perf_counter()
        loss = model.squared_errors(state, action, reward).mean(dim=1).sum()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        optimizer.step()
        seconds += time.perf_counter() - started
        if u % estimate_every == 0 or u == updates:
            new = model.cmi(held[0], held[1], held[3]).numpy()
            new_per_mask = per_mask_variance_cmi(model, held[0], held[1], held[3])
            cmi = new if cmi is None else weight * cmi + (1 - weight) * new
            per_mask = new_per_mask if per_mask is None else weight * per_mask + (1 - weight) * new_per_mask
            with torch.no_grad():
                mse = model.squared_errors(held[0], held[1], held[3]).mean(dim=1)
            trace.append({"update": u, "mse_full": float(mse[0]),
                          "min_parent_cmi": float(new[truth].min()), "max_other_cmi": float(new[~truth].max()),
                          "others_over_threshold": int((new[~truth] >= cfg.reward_threshold).sum()),
                          "per_mask_min_parent_cmi": float(new_per_mask[truth].min()),
                          "per_mask_max_abs_other_cmi": float(np.abs(new_per_mask[~truth]).max()),
                          "per_mask_others_over_threshold": int((new_per_mask[~truth] >= cfg.reward_threshold).sum())})
    return TrainedReward(model, cmi, per_mask, trace, seconds / max(updates, 1))


def evaluate_reward(trained: TrainedReward, spec: EnvSpec, data: dict[str, np.ndarray], threshold: float
                    ) -> dict[str, Any]:
    """Reward parents from the averaged CMI (the model's and the per-mask one), and the abstractions
    they give through the env's true dynamics graph, scored against the truth."""
    n, truth = spec.num_factors, np.asarray(spec.reward_parents)
    true_kept = set(minimal_abstraction(spec.global_graph, spec.reward_parents).kept)
    reward = data["reward"]
    out: dict[str, Any] = {"data": {"nonzero_share": float(np.mean(reward != 0)),
                                    "distinct_values": int(np.unique(reward).size),
                                    "variance": float(reward.var()), "heldout": int(data["heldout"].sum())}}
    for name, cmi in (("reward", trained.reward_cmi), ("per_mask_reward", trained.per_mask_cmi)):
        parents = (cmi >= threshold).astype(np.uint8)
        kept = minimal_abstraction(spec.global_graph, parents).kept
        out[name] = {**binary_scores(parents, truth, np.ones(parents.shape, bool)),
                     "abstraction_accuracy_true_graph": abstraction_accuracy(kept, true_kept, n),
                     "learned": parents.tolist(), "cmi": np.round(cmi, 4).tolist()}
    out["trace"] = trained.trace
    return out


def reward_table(rows: list[dict[str, Any]]) -> str:
    """Mean and sample sd over seeds, as markdown."""
    keys = [("data", "nonzero_share"), ("reward", "f1"), ("reward", "abstraction_accuracy_true_graph"),
            ("per_mask_reward", "f1"), ("per_mask_reward", "abstraction_accuracy_true_graph"),
            ("", "seconds_per_update")]
    lines = ["| seeds | " + " | ".join(f"{b}_{k}" if b else k for b, k in keys) + " |", "|---" * (len(keys) + 1) + "|"]
    cells = []
    for block, key in keys:
        values = np.array([(r[block] if block else r)[key] for r in rows], dtype=float)
        cells.append(f"{values.mean():.3f} ± {values.std(ddof=1):.3f}" if len(values) > 1 else f"{values[0]:.3f}")
    return "\n".join(lines + [f"| {len(rows)} | " + " | ".join(cells) + " |"])


def non_distractor_entries(names: tuple[str, ...]) -> np.ndarray:
    """Off-diagonal entries whose effect and cause (the action counts as one) are not distractors."""
    plain = np.array([not is_distractor(n) for n in names])
    return scored_entries((len(names), len(names) + 1)) & plain[:, None] & np.append(plain, True)[None, :]


def factor_kind(name: str) -> str:
    """``"cd"``, ``"ud"`` (chapter 4's controllable / uncontrollable distractors) or ``"scene"``."""
    return name.split(".", 1)[0] if is_distractor(name) else "scene"


def distractor_errors_by_kind(learned: np.ndarray, truth: np.ndarray, names: tuple[str, ...]) -> dict[str, int]:
    """Wrong off-diagonal entries that involve a distractor, counted by ``"<effect kind> <- <cause kind>"``
    (:func:`factor_kind`; the action column is ``"action"``), e.g. ``"scene <- cd"``: a scene factor
    read from a controllable distractor, the edge that makes a distractor an ancestor of the reward."""
    kinds = [factor_kind(n) for n in names]
    causes = kinds + ["action"]
    wrong = (learned.astype(bool) != truth.astype(bool)) & scored_entries(truth.shape)
    counts: dict[str, int] = {}
    for i, j in zip(*np.nonzero(wrong)):
        if kinds[i] == "scene" and causes[j] in ("scene", "action"):
            continue
        key = f"{kinds[i]} <- {causes[j]}"
        counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items()))


def graph_scores(cmi: np.ndarray, spec: EnvSpec, threshold: float, predicted: np.ndarray | None = None
                 ) -> dict[str, Any]:
    """The graph ``cmi >= threshold`` (or ``predicted``, decided by another rule) scored against the truth;
    ROC AUC and the best-threshold F1 rank ``cmi`` either way."""
    truth = spec.global_graph
    full = score_graph(cmi, truth, threshold, predicted=predicted)
    learned = with_self_edges(cmi >= threshold if predicted is None else predicted)
    mask = non_distractor_entries(spec.factor_names)
    scored = scored_entries(truth.shape)
    return {"accuracy": full["accuracy"], "with_self_accuracy": full["with_self_accuracy"], "f1": full["f1"],
            "best_threshold_f1": full["best_threshold_f1"], "roc_auc": full["roc_auc"],
            "empty_accuracy": float(1 - truth[scored].mean()), "empty_with_self_accuracy": float(1 - truth.mean()),
            "non_distractor_f1": binary_scores(learned, truth, mask)["f1"],
            "non_distractor_accuracy": binary_scores(learned, truth, mask)["accuracy"],
            "distractor_errors": int(((learned != truth.astype(bool)) & scored & ~mask).sum()),
            "distractor_errors_by_kind": distractor_errors_by_kind(learned, truth, tuple(spec.factor_names))}


def abstraction_scores(adjacency: np.ndarray, reward_parents: np.ndarray, spec: EnvSpec) -> dict[str, Any]:
    n = spec.num_factors
    truth = set(minimal_abstraction(spec.global_graph, spec.reward_parents).kept)
    learned = minimal_abstraction(adjacency, reward_parents).kept
    true_reward = minimal_abstraction(adjacency, spec.reward_parents).kept
    cdl = cdl_abstraction(adjacency).kept
    return {"abstraction_accuracy": abstraction_accuracy(learned, truth, n),
            "abstraction_accuracy_true_reward": abstraction_accuracy(true_reward, truth, n),
            "cdl_abstraction_accuracy": abstraction_accuracy(cdl, truth, n),
            "kept": {"truth": sorted(truth), "cbm": list(learned), "cbm_true_reward": list(true_reward), "cdl": list(cdl)}}


def final_estimate(trained: Trained, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                   seed: int) -> EdgeEstimate:
    """The final model's dynamics CMI on every given transition, with standard errors over them: the live
    evaluator's estimate (:class:`causal.methods.cbm.DynamicsCMI`), on all of them where the evaluator
    draws ``cmi_samples`` for the implicit model."""
    return DynamicsCMI(seed).estimate(trained.trainer.model, state, action, next_state, max_samples=state.shape[0])


def fdr_scores(estimate: EdgeEstimate, reward_parents: np.ndarray, spec: EnvSpec, threshold: float, fdr: float,
               min_cmi: float) -> dict[str, Any]:
    """The graph of ``estimate`` decided by the FDR rule (``CMI > min_cmi`` at rate ``fdr``) against the
    fixed ``threshold`` on the same estimate: scores, abstractions and edge counts."""
    edges, _ = decide(estimate, "fdr", threshold, fdr, min_cmi, bias="fixed")
    off = scored_entries(edges.shape)
    return {"fdr": fdr, "min_cmi": min_cmi, "samples": int(estimate.samples),
            "edges": int(edges[off].sum()), "fixed_threshold_edges": int((estimate.cmi >= threshold)[off].sum()),
            "graph": graph_scores(estimate.cmi, spec, threshold, predicted=edges),
            "fixed_threshold_graph": graph_scores(estimate.cmi, spec, threshold),
            **abstraction_scores(with_self_edges(edges), reward_parents, spec),
            "fixed_threshold_abstraction_accuracy_true_reward": abstraction_scores(
                with_self_edges(estimate.cmi >= threshold), reward_parents, spec)["abstraction_accuracy_true_reward"]}


def evaluate(trained: Trained, spec: EnvSpec, data: dict[str, np.ndarray], seed: int,
             extra_negatives: tuple[int, ...], fdr: float = 0.0, fdr_min_cmi: float | None = None
             ) -> dict[str, Any]:
    """Dynamics graph, reward parents and abstractions from the averaged CMI, scored against the truth;
    for the implicit model also one estimate at the default and at each of ``extra_negatives``
    negatives on the same transitions (how much N moves it); with ``fdr`` > 0 the final model's graph
    by the FDR rule (:func:`fdr_scores`; ``fdr_min_cmi`` None: the CMI threshold)."""
    cfg, cmi = trained.trainer.cfg, trained.cmi
    parents = (trained.reward_cmi >= cfg.reward_threshold).astype(np.uint8)
    out = {"graph": graph_scores(cmi, spec, cfg.cmi_threshold),
           "reward": {**binary_scores(parents, spec.reward_parents, np.ones(parents.shape, bool)),
                      "learned": parents.tolist(), "cmi": np.round(trained.reward_cmi, 4).tolist()},
           **abstraction_scores(with_self_edges(cmi >= cfg.cmi_threshold), parents, spec),
           "cmi": np.round(cmi, 4).tolist()}
    s, a, nxt, _ = tensors(data, np.flatnonzero(data["heldout"]))
    model = trained.trainer.model
    if model.implicit and extra_negatives:
        default = model.dynamics_cmi(s, a, nxt, torch.Generator().manual_seed(seed)).numpy()
        for n in extra_negatives:
            again = model.dynamics_cmi(s, a, nxt, torch.Generator().manual_seed(seed), num_negatives=n).numpy()
            out[f"negatives_{n}"] = {"max_abs_cmi_difference": float(np.abs(again - default).max()),
                                     "mean_abs_cmi_difference": float(np.abs(again - default).mean()),
                                     **graph_scores(again, spec, cfg.cmi_threshold)}
    if fdr > 0:
        min_cmi = cfg.cmi_threshold if fdr_min_cmi is None else fdr_min_cmi
        out["fdr"] = fdr_scores(final_estimate(trained, s, a, nxt, seed), parents, spec, cfg.cmi_threshold, fdr,
                                min_cmi)
    return out


def plot_abstractions(spec: EnvSpec, results: dict[str, dict[str, Any]], path: Path, title: str) -> None:
    """Figs. 4.5-4.6: one row per abstraction, one column per factor; kept factors dark."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(results.values()))
    rows = [("true minimal", first["kept"]["truth"])]
    for variant, result in results.items():
        rows += [(f"CBM {variant}", result["kept"]["cbm"]),
                 (f"CBM {variant}, true reward parents", result["kept"]["cbm_true_reward"]),
                 (f"CDL's abstraction of the {variant} graph", result["kept"]["cdl"])]
    grid = np.zeros((len(rows), spec.num_factors))
    for r, (_, kept) in enumerate(rows):
        grid[r, kept] = 1
    fig, ax = plt.subplots(figsize=(max(8, 0.22 * spec.num_factors), 0.5 * len(rows) + 1.6))
    ax.imshow(grid, cmap="Greens", vmin=-0.2, vmax=1.2, aspect="auto")
    ax.set_yticks(range(len(rows)), [name for name, _ in rows], fontsize=8)
    ax.set_xticks(range(spec.num_factors), spec.factor_names, rotation=90, fontsize=7)
    ax.set_title(title + " (dark: kept)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def table(rows: list[dict[str, Any]]) -> str:
    """Mean and sample sd over seeds per variant, as markdown."""
    keys = [("graph", "accuracy"), ("graph", "with_self_accuracy"), ("graph", "empty_with_self_accuracy"),
            ("graph", "f1"), ("graph", "non_distractor_f1"), ("reward", "f1"), ("reward", "accuracy"),
            ("", "abstraction_accuracy"),
            ("", "abstraction_accuracy_true_reward"), ("", "cdl_abstraction_accuracy"), ("", "seconds_per_update")]
    names = [f"{block}_{key}" if block == "reward" else key for block, key in keys]
    lines = ["| variant | seeds | " + " | ".join(names) + " |", "|---" * (len(keys) + 2) + "|"]
    for variant in dict.fromkeys(r["variant"] for r in rows):
        mine = [r for r in rows if r["variant"] == variant]
        cells = []
        for block, key in keys:
            values = np.array([(r[block] if block else r)[key] for r in mine], dtype=float)
            cells.append(f"{values.mean():.3f} ± {values.std(ddof=1):.3f}" if len(values) > 1 else f"{values[0]:.3f}")
        lines.append(f"| {variant} | {len(mine)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def merge_tables(paths: list[Path]) -> dict[str, Any]:
    """One table from several runs' ``cbm_table.json`` (rows concatenated, sorted by variant and seed);
    ``ValueError`` if their factors differ or a (variant, seed) repeats."""
    tables = [json.loads(path.read_text()) for path in paths]
    names = tables[0]["factor_names"]
    if any(t["factor_names"] != names for t in tables):
        raise ValueError(f"the tables {[str(p) for p in paths]} were learned on different factors")
    rows = [row for t in tables for row in t["rows"]]
    keys = [(r["variant"], r["seed"]) for r in rows]
    if len(set(keys)) != len(keys):
        raise ValueError(f"a (variant, seed) appears twice in {[str(p) for p in paths]}")
    order = list(dict.fromkeys(r["variant"] for r in rows))
    rows.sort(key=lambda r: (order.index(r["variant"]), r["seed"]))
    return {"args": [t["args"] for t in tables], "factor_names": names, "rows": rows}


def scene_kwargs(env: str, distractors: str, task: str, graph: str = "full", num_objects: int = 3,
                 episode_length: int = 0, velocities: bool = False) -> dict[str, Any]:
    """The keyword arguments of ``make_env(env, ...)`` for these settings (a table's ``args`` name them):
    ``graph`` and ``num_objects`` on Chemical only, ``episode_length`` 0 for the env's own."""
    kwargs: dict[str, Any] = dict(distractors=distractors, task=task)
    if env == "chemical-distractors":
        kwargs |= dict(graph=graph, num_objects=num_objects)
    if episode_length:
        kwargs["episode_length"] = episode_length
    if velocities:
        kwargs["velocities"] = True
    return kwargs


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="chemical-distractors", choices=("chemical-distractors", "block", "tool-use", "dmc-walker", "dmc-cheetah"))
    p.add_argument("--num-objects", type=int, default=3)
    p.add_argument("--graph", default="full")
    p.add_argument("--distractors", default="5,5")
    p.add_argument("--task", default="match", help="chemical-distractors: match (every object) or match-first "
                                                    "(object 0 only); block: pick or stack; tool-use: series; dmc-walker: walk, stand or run; dmc-cheetah: run")
    p.add_argument("--episode-length", type=int, default=0, help="steps per episode (0: the env's default)")
    p.add_argument("--steps", type=int, default=20_000, help="random-policy transitions per seed")
    p.add_argument("--grasp", choices=("mov1", "all"), default="mov1",
                   help="block: the scripted grasp that opens every other episode takes mov1, or one of "
                        "mov1-mov3 drawn per episode (all), so that every movable cube is touched")
    p.add_argument("--velocities", action="store_true",
                   help="block, tool-use: velocity factors for the arm, fingers and movable bodies (a Markov state; "
                        "not the chapter's)")
    p.add_argument("--updates", type=int, default=5_000)
    p.add_argument("--estimate-every", type=int, default=500,
                   help="updates between CMI estimates (averaged, and the causal term's parents)")
    p.add_argument("--ema", type=float, default=0.999, help="moving-average weight per update (the evaluator's)")
    p.add_argument("--lr", type=float, default=CBMConfig.lr)
    p.add_argument("--l2", type=float, default=CBMConfig.score_l2,
                   help="lambda1 = lambda2 of eq. 4.5 (the implicit model's penalties on scores and their "
                        "gradients; the reference's 1e-6)")
    p.add_argument("--target", choices=TARGETS, default=CBMConfig.target,
                   help="implicit dynamics' candidates: each factor's change (the authors' code), its next value "
                        "(eq. 4.1's label) or per factor the one that varies less (auto); CBMConfig.target. "
                        "The explicit variant takes the same label (changes under auto)")
    p.add_argument("--explicit-target", choices=("delta", "next"), default=None,
                   help="the explicit variant's label if not --target's: delta is CDL's own model (the "
                        "explicit rows measured before the label applied to both variants)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--variants", nargs="+", default=["implicit", "explicit"])
    p.add_argument("--extra-negatives", type=int, nargs="*", default=[1024],
                   help="also estimate the implicit CMI with these numbers of negatives (sensitivity)")
    p.add_argument("--fdr", type=float, default=0.0,
                   help="also decide the final model's graph by the FDR rule at this rate (0: off; module docstring)")
    p.add_argument("--fdr-min-cmi", type=float, default=None,
                   help="the FDR rule's smallest effect, CMI > this (default: the 0.02-nat CMI threshold)")
    p.add_argument("--reward-only", action="store_true",
                   help="train and score the causal reward model alone (no dynamics): cbm_reward.json")
    p.add_argument("--out", type=Path, default=Path("benchmark-results/cbm_table"))
    p.add_argument("--merge", type=Path, nargs="+", default=None,
                   help="instead of training: merge these cbm_table.json files (one run per seed, the same "
                        "factors) into <out>/cbm_table.json and print their table")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.merge:
        merged = merge_tables(args.merge)
        (args.out / "cbm_table.json").write_text(json.dumps(merged, indent=1))
        print(table(merged["rows"]))
        return
    try:  # settings the models would refuse, refused before minutes of collection
        CBMConfig(lr=args.lr, target=args.target, score_l2=args.l2, grad_l2=args.l2)
    except ValueError as error:
        p.error(str(error))
    if not 0.0 <= args.fdr < 1.0 or (args.fdr_min_cmi is not None and not args.fdr_min_cmi >= 0.0):
        p.error(f"--fdr must be in [0, 1) and --fdr-min-cmi >= 0, got {args.fdr}, {args.fdr_min_cmi}")
    if args.fdr and args.reward_only:
        p.error("--fdr decides the dynamics graph, which --reward-only does not train")
    if args.grasp != "mov1" and args.env != "block":
        p.error("--grasp applies to --env block only")
    if args.velocities and args.env not in ("block", "tool-use"):
        p.error("--velocities applies to --env block and tool-use only")
    grasp_targets = BLOCK_CUBES if args.grasp == "all" else ("mov1",)
    env_kwargs = scene_kwargs(args.env, args.distractors, args.task, args.graph, args.num_objects,
                              args.episode_length, args.velocities)
    rows: list[dict[str, Any]] = []
    if args.reward_only:
        cfg = CBMConfig(lr=args.lr)
        for seed in args.seeds:
            spec, data = collect(env_kwargs, args.steps, seed, args.env, grasp_targets)
            trained_reward = train_reward(spec, cfg, data, args.updates, args.estimate_every, args.ema, seed)
            rows.append({"seed": seed, "seconds_per_update": trained_reward.seconds_per_update,
                         **evaluate_reward(trained_reward, spec, data, cfg.reward_threshold)})
            print(f"seed {seed}: {json.dumps({k: rows[-1][k] for k in ('data', 'reward', 'per_mask_reward')})}",
                  flush=True)
            (args.out / "cbm_reward.json").write_text(json.dumps({"args": vars(args) | {"out": str(args.out)},
                                                                   "factor_names": spec.factor_names,
                                                                   "rows": rows}, indent=1))
        print(reward_table(rows))
        return
    for seed in args.seeds:
        spec, data = collect(env_kwargs, args.steps, seed, args.env, grasp_targets)
        results = {}
        for variant in args.variants:
            target = args.explicit_target if variant == "explicit" and args.explicit_target else args.target
            cfg = CBMConfig(dynamics=variant, lr=args.lr, target=target, score_l2=args.l2, grad_l2=args.l2)
            trained = train(spec, cfg, data, args.updates, args.estimate_every, args.ema, seed)
            results[variant] = evaluate(trained, spec, data, seed, tuple(args.extra_negatives), args.fdr,
                                        args.fdr_min_cmi)
            rows.append({"variant": variant, "seed": seed, "target": target,
                         "seconds_per_update": trained.seconds_per_update, **results[variant]})
            print(f"seed {seed} {variant}: {json.dumps({k: rows[-1][k] for k in ('graph', 'abstraction_accuracy')})}",
                  flush=True)
            if "fdr" in rows[-1]:
                f = rows[-1]["fdr"]
                print(f"seed {seed} {variant}, final model on {f['samples']} held-out transitions: FDR {f['fdr']} "
                      f"(CMI > {f['min_cmi']}) {f['edges']} edges, accuracy {f['graph']['accuracy']:.3f}, "
                      f"abstraction (true reward parents) {f['abstraction_accuracy_true_reward']:.3f}; fixed "
                      f"threshold {f['fixed_threshold_edges']} edges, {f['fixed_threshold_graph']['accuracy']:.3f}, "
                      f"{f['fixed_threshold_abstraction_accuracy_true_reward']:.3f}", flush=True)
            (args.out / "cbm_table.json").write_text(json.dumps({"args": vars(args) | {"out": str(args.out)},
                                                                  "factor_names": spec.factor_names,
                                                                  "rows": rows}, indent=1))
        scene = f"{args.num_objects} objects, " if args.env == "chemical-distractors" else ""
        plot_abstractions(spec, results, args.out / f"cbm_abstractions_s{seed}.png",
                          f"{args.env} {args.task}, {scene}distractors {args.distractors}, seed {seed}")
    print(table(rows))


if __name__ == "__main__":
    main()
