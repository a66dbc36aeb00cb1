"""`make lint` in the suite: pyflakes finds nothing in the packages, the benchmarks or the tests (unused
imports, undefined names, star imports that hide them), so a green `make test` means a clean lint."""
from __future__ import annotations

from pathlib import Path

from pyflakes.api import checkPath
from pyflakes.reporter import Reporter

REPO = Path(__file__).resolve().parents[1]
LINTED = ("services", "proto", "envs", "causal", "benchmarks", "tests")
"""The folders `make lint` checks (Makefile)."""


class _Collect(Reporter):
    def __init__(self) -> None:
        self.lines: list[str] = []

    def unexpectedError(self, filename: str, msg: str) -> None:
        self.lines.append(f"{filename}: {msg}")

    def syntaxError(self, filename: str, msg: str, lineno: int, offset: int | None, text: str | None) -> None:
        self.lines.append(f"{filename}:{lineno}: {msg}")

    def flake(self, message) -> None:
        self.lines.append(str(message))


def test_pyflakes_finds_nothing() -> None:
    reporter = _Collect()
    files = sorted(p for folder in LINTED for p in (REPO / folder).rglob("*.py"))
    assert len(files) > 100
    for path in files:
        checkPath(str(path), reporter)
    assert not reporter.lines, "\n".join(reporter.lines)


def test_the_makefile_lints_the_same_folders() -> None:
    lint = next(line for line in (REPO / "Makefile").read_text().splitlines() if "-m pyflakes" in line)
    assert sorted(lint.split("-m pyflakes", 1)[1].split()) == sorted(LINTED)
