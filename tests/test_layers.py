"""The package structure DESIGN.md asks for: imports point downwards (services -> causal -> envs ->
proto), no import cycles (counting imports inside functions too), and no service names a method."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("proto", "envs", "causal", "services")
"""Lowest first: a package may import only from itself and the packages before it."""


def _modules() -> dict[str, Path]:
    out = {}
    for package in LAYERS:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = _modules()


def _imports(path: Path) -> set[str]:
    """Project modules ``path`` imports anywhere in its body (module level or inside functions)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # ``from package import submodule`` depends on the submodule, not on the package's other parts
            names = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in MODULES else node.module
                     for alias in node.names]
        found |= {name for name in names if name in MODULES}
    return found


GRAPH = {module: _imports(path) - {module} for module, path in MODULES.items()}


def test_imports_point_downwards() -> None:
    wrong = [(module, target) for module, targets in GRAPH.items() for target in targets
             if LAYERS.index(target.split(".")[0]) > LAYERS.index(module.split(".")[0])]
    assert not wrong, f"imports that point upwards: {wrong}"


def test_no_import_cycles() -> None:
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for target in sorted(GRAPH[module]):
            if state.get(target) == 1:
                cycles.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target, path + [target])
        state[module] = 2

    for module in sorted(GRAPH):
        if module not in state:
            visit(module, [module])
    assert not cycles, f"import cycles: {cycles}"


@pytest.mark.parametrize("service", sorted(p.name for p in (ROOT / "services").iterdir() if p.is_dir()
                                           and not p.name.startswith("_")))
def test_no_service_imports_a_particular_method(service: str) -> None:
    """Services reach methods through ``causal.methods`` (the registry) and ``causal.method`` (the
    roles) only; a method's own modules (``causal.cdl``, ``causal.methods.cdl``, ...) are its business.
    The chapter-3 post-run evaluation suite is the one place that names Chemical's CDL evaluation."""
    particular = {"causal.cdl", "causal.cdl_trainer", "causal.baselines"} | {
        m for m in MODULES if m.startswith("causal.methods.")}
    for path in sorted((ROOT / "services" / service).rglob("*.py")):
        assert not (_imports(path) & particular), f"{path.relative_to(ROOT)} imports {_imports(path) & particular}"
