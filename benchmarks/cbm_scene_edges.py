"""The scene's own edges in :mod:`benchmarks.cbm_graph_table` runs: precision and recall on the entries
whose effect and cause are not distractors, the edges one run has and another lacks, and how often
the collection policy moves each cube.

Why it exists: with the contact-union truth most scene entries are edges, so a spurious scene edge
usually scores as a true positive and the scene F1 alone can mislead (docs/results.md, "The explicit
variant with next values, and shorter collection episodes").

    .venv/bin/python -m benchmarks.cbm_scene_edges --tables A/cbm_table.json B/cbm_table.json
    .venv/bin/python -m benchmarks.cbm_scene_edges --compare A/cbm_table.json B/cbm_table.json
    .venv/bin/python -m benchmarks.cbm_scene_edges --moves 6000 --episode-lengths 0 100

Each table's truth is its env's (built from the table's ``args``); the first row of a table is read.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.cbm_graph_table import BLOCK_CUBES, collect, non_distractor_entries, scene_kwargs
from causal.abstraction import with_self_edges
from causal.cbm_config import CBMConfig
from causal.graph_metrics import confusion
from envs.registry import make_env
from proto.messages import EnvSpec

THRESHOLD = CBMConfig.cmi_threshold  # chapter 4's dynamics edge threshold, as cbm_graph_table scores it


def scene_scores(cmi: np.ndarray, truth: np.ndarray, names: tuple[str, ...], threshold: float = THRESHOLD
                 ) -> dict[str, float | int]:
    """True / false positives, false negatives, precision and recall of ``cmi >= threshold`` (self edges
    added, as the benchmark does) on the non-distractor off-diagonal entries."""
    learned, truth = with_self_edges(np.asarray(cmi) >= threshold), np.asarray(truth, bool)
    mask = non_distractor_entries(names)
    c = confusion(learned, truth, mask)
    return {"true": int((truth & mask).sum()), "tp": c["tp"], "fp": c["fp"], "fn": c["fn"],
            "precision": c["tp"] / max(c["tp"] + c["fp"], 1), "recall": c["tp"] / max(c["tp"] + c["fn"], 1)}


def edges_only_in(cmi: np.ndarray, other: np.ndarray, names: tuple[str, ...], threshold: float = THRESHOLD
                  ) -> list[str]:
    """Non-distractor edges ``effect<-cause`` of ``cmi`` that ``other`` lacks (the last column is the action)."""
    mask = non_distractor_entries(names)
    a, b = (with_self_edges(np.asarray(c) >= threshold).astype(bool) & mask for c in (cmi, other))
    columns = list(names) + ["action"]
    return sorted(f"{names[i]}<-{columns[j]}" for i, j in zip(*np.nonzero(a & ~b)))


def moved_share(data: dict[str, np.ndarray], names: tuple[str, ...], bodies: tuple[str, ...] = BLOCK_CUBES,
                tolerance: float = 1e-3) -> dict[str, float]:
    """Share of transitions in which each body's ``x``/``y``/``z`` changes by more than ``tolerance``."""
    change = np.abs(data["next_state"] - data["state"])
    return {body: float((change[:, [names.index(f"{body}.{c}") for c in "xyz"]].max(axis=1) > tolerance).mean())
            for body in bodies}


def _table_spec(args: dict[str, Any], cache: dict[tuple, EnvSpec]) -> EnvSpec:
    key = (args["env"], args["task"], args["distractors"], args["graph"], args["num_objects"],
           bool(args.get("velocities")))
    if key not in cache:
        kwargs = scene_kwargs(args["env"], args["distractors"], args["task"], args["graph"], args["num_objects"],
                              velocities=bool(args.get("velocities")))
        env = make_env(args["env"], **kwargs).unwrapped
        cache[key] = env.env_spec()
        env.close()
    return cache[key]


def _first_row(path: Path) -> tuple[dict[str, Any], np.ndarray]:
    table = json.loads(path.read_text())
    return table["args"], np.asarray(table["rows"][0]["cmi"])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tables", type=Path, nargs="*", default=[], help="cbm_table.json files to score")
    p.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"), help="edges each of two tables has alone")
    p.add_argument("--moves", type=int, default=0, help="block steps to collect for the cubes' moved shares")
    p.add_argument("--episode-lengths", type=int, nargs="+", default=[0, 100], help="with --moves (0: the env's)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if not (args.tables or args.compare or args.moves):
        p.error("give --tables, --compare or --moves")
    missing = [str(t) for t in args.tables + list(args.compare or ()) if not t.is_file()]
    if missing:
        p.error(f"no such table: {', '.join(missing)}")
    cache: dict[tuple, EnvSpec] = {}
    for path in args.tables:
        table_args, cmi = _first_row(path)
        spec = _table_spec(table_args, cache)
        s = scene_scores(cmi, np.asarray(spec.global_graph), tuple(spec.factor_names))
        print(f"{path}: true {s['true']} tp {s['tp']} fp {s['fp']} fn {s['fn']} "
              f"precision {s['precision']:.2f} recall {s['recall']:.2f}")
    if args.compare:
        (a_args, a), (_, b) = (_first_row(t) for t in args.compare)
        names = tuple(_table_spec(a_args, cache).factor_names)
        for label, x, y in (("only in A", a, b), ("only in B", b, a)):
            print(f"{label}: {', '.join(edges_only_in(x, y, names)) or '-'}")
    for length in args.episode_lengths if args.moves else ():
        spec, data = collect(scene_kwargs("block", "20,20", "pick", episode_length=length), args.moves, args.seed,
                             "block", BLOCK_CUBES)
        shares = moved_share(data, tuple(spec.factor_names))
        print(f"episode length {length or 'default'}: " + ", ".join(f"{k} moved in {v:.3f}" for k, v in shares.items()))


if __name__ == "__main__":
    main()
