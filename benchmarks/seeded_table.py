"""The command line every seeded table benchmark shares: a budget dataclass as flags, seeds, a JSON file.

A benchmark gives its ``Budget`` (integer fields, each becoming ``--field-name``), a default output
path, ``run_seed(seed, budget, args, save)`` and ``table(results)``; :func:`table_main` parses the
flags, runs the seeds one after another with one torch thread, rewrites the JSON after every seed
(and whenever ``run_seed`` calls ``save`` with a partial record, so a long seed leaves what it has
measured so far), and prints the table. ``--merge FILE ...`` prints one table over earlier runs'
files (seeds run in separate processes) instead.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any, Callable

import torch

Record = dict[str, Any]
SaveFn = Callable[[Record], None]


def table_main(argv: list[str] | None, *, description: str | None, budget_type: type, default_out: Path,
               run_seed: Callable[[int, Any, argparse.Namespace, SaveFn], Record],
               table: Callable[[list[Record]], str],
               add_arguments: Callable[[argparse.ArgumentParser], None] = lambda _: None) -> list[Record]:
    """Run ``run_seed`` for every ``--seeds`` entry and return the records (also written to ``--out``).

    ``--merge FILE ...`` instead prints one table over the records of earlier runs' ``--out`` files (seeds
    run in separate processes) and returns them, running nothing."""
    args_list = sys.argv[1:] if argv is None else argv
    if args_list[:1] == ["--merge"]:
        return merge_main(args_list, description, table)
    p = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    fields = dataclasses.fields(budget_type)
    for f in fields:
        p.add_argument(f"--{f.name.replace('_', '-')}", type=int, default=f.default)
    add_arguments(p)
    p.add_argument("--out", type=Path, default=default_out)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    budget = budget_type(**{f.name: getattr(args, f.name) for f in fields})
    results: list[Record] = []
    args.out.parent.mkdir(parents=True, exist_ok=True)

    def save(partial: Record | None = None) -> None:
        done = results + ([partial] if partial is not None else [])
        args.out.write_text(json.dumps({"budget": dataclasses.asdict(budget), "results": done}, indent=1))

    for seed in args.seeds:
        results.append(run_seed(seed, budget, args, save))
        save()
    print(table(results))
    return results


def merge_main(argv: list[str], description: str | None, table: Callable[[list[Record]], str]) -> list[Record]:
    """``--merge FILE ...``: the records of the given ``--out`` files in one table (files checked first)."""
    p = argparse.ArgumentParser(description=f"one table over earlier runs' --out files. {description or ''}",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--merge", nargs="+", type=Path, required=True, help="the runs' --out files")
    paths = p.parse_args(argv).merge
    if missing := [str(path) for path in paths if not path.is_file()]:
        p.error(f"no such file: {', '.join(missing)}")
    records = [record for path in paths for record in json.loads(path.read_text())["results"]]
    print(table(records))
    return records
