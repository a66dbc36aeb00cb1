"""Which credentials an operator command connects with: --bus-credentials, the run dir's, the environment."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from services.bus.credentials import Credentials, read_credentials, role_file, write_run_secrets
from services.bus.roles import access_control, new_passwords, run_roles
from services.ops.target import OpsError, resolve_target


def _args(**flags: str | None) -> argparse.Namespace:
    return argparse.Namespace(**{"connect": None, "run_id": None, "run_dir": None, "bus_credentials": None, **flags})


def test_a_run_dir_with_secrets_gives_the_operator_credentials(tmp_path: Path) -> None:
    (tmp_path / "config.json").write_text(json.dumps({"run_id": "r", "router_port": 7555, "bus_auth": True}))
    passwords = new_passwords()
    write_run_secrets(tmp_path, passwords, access_control(run_roles("r", "cdl")))
    target = resolve_target(_args(run_dir=str(tmp_path)), environ={})
    assert target.credentials == Credentials("operator", passwords["operator"])
    (tmp_path / "config.json").write_text(json.dumps({"run_id": "r", "router_port": 7555, "bus_auth": False}))
    assert resolve_target(_args(run_dir=str(tmp_path)), environ={}).credentials is None  # resumed without auth


def test_explicit_file_then_environment_then_none(tmp_path: Path) -> None:
    own, env = tmp_path / "own", tmp_path / "env"
    own.write_text("operator:a\n")
    env.write_text("operator:b\n")
    environ = {"CAUSEWAY_BUS_CREDENTIALS": str(env)}
    assert resolve_target(_args(run_id="r", bus_credentials=str(own)), environ).credentials == Credentials("operator", "a")
    assert resolve_target(_args(run_id="r"), environ).credentials == Credentials("operator", "b")
    assert resolve_target(_args(run_id="r"), environ={}).credentials is None


@pytest.mark.parametrize("text", ["", "operator", "operator:", ":pw", "a:b\nc:d"])
def test_a_malformed_credentials_file_is_refused_by_name(tmp_path: Path, text: str) -> None:
    path = tmp_path / "bad"
    path.write_text(text)
    with pytest.raises(ValueError, match=str(path)):
        read_credentials(path)
    with pytest.raises(OpsError, match="bad"):
        resolve_target(_args(run_id="r", bus_credentials=str(path)), environ={})


def test_role_files_live_in_the_run_dir_secrets(tmp_path: Path) -> None:
    assert role_file(tmp_path, "env-worker") == tmp_path / "secrets" / "env-worker.credentials"
