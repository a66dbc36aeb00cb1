"""Every command the docs quote parses with today's CLI; nothing is run.

Commands are taken from README.md and docs/**/*.md: each line of a fenced code block (``\\``
continuations joined, ``# comments`` dropped) and each inline code span. Recognised forms:

- ``causeway <command> ...``, ``.venv/bin/causeway ...``, ``python -m services.cli ...``
  (``python``, ``python3`` or ``.venv/bin/python``): parsed by ``services.cli.main``;
- ``make <target> [VAR=...] [ARGS="..."]``: the target must exist in the Makefile, and where its
  recipe runs ``services.cli`` or a benchmark, that command (with ``$(ARGS)`` expanded) is checked;
- ``python -m benchmarks.<name> ...``: the module must exist, and its flags parse when it has an
  argparse parser;
- ``pytest ... tests/...``: the test files exist.

Placeholders are filled in first: ``<N>`` becomes 1, any other ``<word>`` becomes ``word``, a lone
capital (``N``, ``R``, ``S``) becomes 2, optional ``[...]`` parts are kept, ``...`` is dropped.

"Parses" means: the command's own entry point runs with ``argparse.ArgumentParser.parse_args``
patched to stop the program (``_Parsed``) as soon as a parse succeeds, so an unknown flag or a bad
value fails the test and nothing after parsing (a bus, a run, a benchmark) ever starts.

Also: every relative link of those pages points at a file, and at a heading of it, that exists.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import os
import re
import runpy
import shlex
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
PYTHONS = {"python", "python3", ".venv/bin/python"}
CAUSEWAYS = {"causeway", ".venv/bin/causeway"}


@dataclass(frozen=True)
class Quoted:
    """One command quoted in a doc."""

    where: str
    """``file:line`` of the quote."""
    text: str
    """The command as written."""


# ---------------------------------------------------------------------------------------------
# finding the commands


FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
INLINE = re.compile(r"`([^`\n]+(?:\n[^`\n]+)*)`")
STARTS = re.compile(r"^(?:causeway |\.venv/bin/causeway |(?:\.venv/bin/)?python3? -m (?:services\.cli|benchmarks\.)"
                    r"|make |pytest )")


def quoted_commands(path: Path) -> list[Quoted]:
    """The commands quoted in one markdown file (fenced lines and inline spans)."""
    text = path.read_text()
    name = path.relative_to(ROOT).as_posix()
    found: list[Quoted] = []

    def line_of(offset: int) -> int:
        return text.count("\n", 0, offset) + 1

    for block in FENCE.finditer(text):
        joined = re.sub(r"\\\n\s*", " ", block.group(1))
        start = line_of(block.start(1))
        for k, line in enumerate(joined.splitlines()):
            line = line.strip()
            if STARTS.match(line):
                found.append(Quoted(f"{name}:{start + k}", line))
    prose = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)  # keeps line numbers
    for span in INLINE.finditer(prose):
        command = " ".join(span.group(1).split())
        if STARTS.match(command):
            found.append(Quoted(f"{name}:{line_of(span.start())}", command))
    return found


def fill_placeholders(command: str) -> list[str]:
    """The command's words with placeholders replaced by plausible values."""
    command = re.sub(r"<N>", "1", command)
    command = re.sub(r"<([^<>\s]+)>", r"\1", command)
    command = command.replace("[", " ").replace("]", " ")
    words = shlex.split(command, comments=True)
    return [("2" if re.fullmatch(r"[A-Z]", w) else w) for w in words if w not in ("...", "…")]


QUOTED = [q for path in DOCS if path.exists() for q in quoted_commands(path)]


# ---------------------------------------------------------------------------------------------
# checking one command


class _Parsed(Exception):
    """Raised by the patched ``parse_args`` once a command line parsed."""


class CommandError(AssertionError):
    """A quoted command that the current code does not accept."""


@contextlib.contextmanager
def parse_only():
    """Patch ``ArgumentParser`` to stop the program after a successful parse.

    ``parse_args`` stops with the namespace; ``parse_known_args`` called directly (a benchmark that
    passes the flags it does not know on to ``causeway run``) stops with the namespace and the rest."""
    originals = argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args
    inside = []

    def parse_args(self, args=None, namespace=None):
        inside.append(True)
        try:
            parsed = originals[0](self, args, namespace)
        finally:
            inside.pop()
        raise _Parsed(parsed, [])

    def parse_known_args(self, args=None, namespace=None):
        parsed, rest = originals[1](self, args, namespace)
        if inside:
            return parsed, rest
        raise _Parsed(parsed, rest)

    argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args = parse_args, parse_known_args
    try:
        yield
    finally:
        argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args = originals


def expect_parse(entry, describe: str) -> list[str]:
    """Run ``entry()`` under :func:`parse_only`; ``CommandError`` unless it parsed (or printed --help).
    Returns the words a ``parse_known_args`` left over."""
    err = io.StringIO()
    try:
        with parse_only(), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            entry()
    except _Parsed as parsed:
        return parsed.args[1]
    except SystemExit as exc:
        if exc.code in (0, None):
            return []  # --help
        raise CommandError(f"{describe}: rejected: {err.getvalue().strip() or exc.code}") from None
    raise CommandError(f"{describe}: returned without parsing any flags: {err.getvalue().strip()}")


def check_cli(argv: list[str]) -> None:
    """``causeway <argv>``, through the CLI's own dispatch."""
    from services import cli

    if not argv or argv[0] not in cli.COMMANDS:
        raise CommandError(f"causeway {' '.join(argv)}: no such command (have: {', '.join(cli.COMMANDS)})")
    rest = expect_parse(lambda: cli.main(argv), "causeway " + " ".join(argv))
    if rest:
        raise CommandError(f"causeway {' '.join(argv)}: not understood: {rest}")


def check_benchmark(module: str, args: list[str]) -> None:
    """``python -m <module> <args>``: the module exists; its flags parse if it has a parser (the
    flags a ``parse_known_args`` leaves over are passed on to ``causeway run``: bench_time_to_f1)."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise CommandError(f"python -m {module}: no such module")
    if not re.search(r"parse_(known_)?args\(|table_main\(", Path(spec.origin).read_text()):
        if args:
            raise CommandError(f"python -m {module}: takes no flags (no parse_args or table_main), the doc gives {args}")
        return
    saved = sys.argv
    sys.argv = [spec.origin, *args]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # runpy: the module was imported before (by another)
            rest = expect_parse(lambda: runpy.run_module(module, run_name="__main__"),
                                f"python -m {module} {' '.join(args)}")
    finally:
        sys.argv = saved
    if rest:
        check_cli(["run", *rest])


def make_recipe(target: str) -> list[str]:
    """The recipe lines of ``target`` in the Makefile (continuations joined)."""
    text = re.sub(r"\\\n\s*", " ", (ROOT / "Makefile").read_text())
    match = re.search(rf"^{re.escape(target)}:[^=\n]*\n((?:\t[^\n]*\n?)*)", text, re.M)
    if match is None:
        raise CommandError(f"make {target}: no such target in the Makefile")
    return [line.strip() for line in match.group(1).splitlines() if line.strip()]


def check_make(words: list[str]) -> None:
    """``make <target> [VAR=value ...]``: the target exists; its services.cli / benchmark command parses."""
    targets = [w for w in words[1:] if "=" not in w]
    variables = dict(w.split("=", 1) for w in words[1:] if "=" in w)
    for target in targets:
        for line in make_recipe(target):
            line = line.replace("$(PY)", "python").replace("$(ARGS)", variables.get("ARGS", ""))
            recipe = shlex.split(line)
            if recipe[:3] == ["python", "-m", "services.cli"] or (
                    recipe[:2] == ["python", "-m"] and recipe[2].startswith("benchmarks.")):
                check_words(recipe)


def check_words(words: list[str]) -> None:
    """Dispatch one command (already split into words) to its checker."""
    if words[0] in CAUSEWAYS:
        check_cli(words[1:])
    elif words[0] in PYTHONS and words[1:3] == ["-m", "services.cli"]:
        check_cli(words[3:])
    elif words[0] in PYTHONS and words[1] == "-m" and words[2].startswith("benchmarks."):
        check_benchmark(words[2], words[3:])
    elif words[0] == "make":
        check_make(words)
    elif words[0] == "pytest":
        missing = [w for w in words[1:] if w.startswith("tests/") and not (ROOT / w.split("::")[0]).exists()]
        if missing:
            raise CommandError(f"pytest: no such test file {missing}")
    else:
        raise CommandError(f"not a command this test knows: {' '.join(words)}")


def check_command(command: str) -> None:
    check_words(fill_placeholders(command))


# ---------------------------------------------------------------------------------------------
# the tests


@pytest.fixture(autouse=True)
def _no_causeway_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """``causeway run`` reads CAUSEWAY_* variables: the docs' commands must parse without them."""
    for key in [k for k in os.environ if k.startswith("CAUSEWAY_")]:
        monkeypatch.delenv(key)


@pytest.mark.parametrize("quoted", QUOTED, ids=[f"{q.where} {q.text[:60]}" for q in QUOTED])
def test_quoted_command_parses(quoted: Quoted) -> None:
    try:
        check_command(quoted.text)
    except CommandError as exc:
        pytest.fail(f"{quoted.where}: {exc}", pytrace=False)


def test_the_docs_quote_the_main_commands() -> None:
    """The extraction finds what the README must show (guards against a regex that finds nothing)."""
    readme = {q.text.split("#")[0].strip() for q in QUOTED if q.where.startswith("README.md")}
    assert {"make run", "make test"} <= readme
    assert sum(q.text.startswith((".venv/bin/causeway run", "causeway run")) for q in QUOTED) >= 5
    assert any("benchmarks." in q.text for q in QUOTED)


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def anchors(path: Path) -> set[str]:
    """GitHub's anchors for the headings of a markdown file (outside code blocks)."""
    prose = FENCE.sub("", path.read_text())
    return {re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            for m in re.finditer(r"^#+ (.+)$", prose, re.M)}


def broken_links(path: Path) -> list[str]:
    """Relative links of ``path`` whose file (or heading anchor) does not exist."""
    broken = []
    for target in LINK.findall(FENCE.sub("", path.read_text())):
        if re.match(r"[a-z]+:", target):
            continue  # http:, https:, mailto:
        file, _, anchor = target.partition("#")
        resolved = (path.parent / file).resolve() if file else path
        if not resolved.exists():
            broken.append(target)
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(target)
    return broken


@pytest.mark.parametrize("path", DOCS, ids=[p.relative_to(ROOT).as_posix() for p in DOCS])
def test_relative_links_resolve(path: Path) -> None:
    assert broken_links(path) == []


@pytest.mark.parametrize("command", [
    "causeway run --no-such-flag 1",
    "causeway run --seed not-a-number",
    "causeway status --no-such-flag",
    "causeway scale env-worker N --no-such-flag",
    "causeway final-graph",  # --run-dir is required
    "causeway no-such-command",
    "python -m benchmarks.rescore_runs runs/x --no-such-flag",
    "python -m benchmarks.no_such_benchmark",
    "make no-such-target",
    'make run ARGS="--no-such-flag 1"',
    'make bench-f1 ARGS="--no-such-flag 1"',  # passed on to causeway run
])
def test_a_wrong_command_fails(command: str) -> None:
    with pytest.raises(CommandError):
        check_command(command)


@pytest.mark.parametrize("command", [
    "causeway run --seed 3 --workers 2",
    "causeway status --run-dir runs/<id> [--json]",
    "causeway scale env-worker N --compose-project P",
    "causeway final-graph --run-dir runs/<id>",
    ".venv/bin/python -m benchmarks.rescore_runs runs/manip-ev-s<N> runs/x --graph final --mean",
    "make test",
    'make bench-f1 ARGS="--graphs full"',
])
def test_a_right_command_passes(command: str) -> None:
    check_command(command)
