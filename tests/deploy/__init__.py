"""Tests of the Compose deployment (compose.yaml, deploy/): validated with the real tools.

``docker-compose`` (1.29, Debian) and ``promtool`` (Prometheus 2.42) are installed by
``make sysdeps``; a test that needs one is skipped, saying so, only where it is missing.

YAML is read without a Python dependency of our own: ``docker-compose`` is a Python program that
depends on PyYAML, so the interpreter named in its shebang can turn YAML into JSON.
"""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
_YAML_TO_JSON = "import json, sys, yaml; json.dump(yaml.safe_load(sys.stdin), sys.stdout)"


def require_tool(name: str) -> str:
    """Path of the executable ``name``, or skip the test (``make sysdeps`` installs it)."""
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"{name} is not installed (make sysdeps installs it)")
    return path


def yaml_interpreter() -> str:
    """The Python interpreter that runs docker-compose, which always has PyYAML."""
    shebang = Path(require_tool("docker-compose")).read_bytes()[:200].split(b"\n", 1)[0].decode()
    if not shebang.startswith("#!"):
        pytest.skip("docker-compose is not a Python script here: no PyYAML interpreter to borrow")
    return shebang[2:].strip().split()[-1] if "env" in shebang else shebang[2:].strip()


def load_yaml(text: str) -> Any:
    """``text`` parsed as YAML (safe loader, anchors and merge keys resolved)."""
    result = subprocess.run([yaml_interpreter(), "-c", _YAML_TO_JSON], input=text, capture_output=True,
                            text=True, timeout=30)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def load_yaml_file(relative: str) -> Any:
    """The YAML file at ``relative`` (from the repository root), parsed."""
    return load_yaml((REPO / relative).read_text())
