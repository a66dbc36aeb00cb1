"""``causeway bus-secrets``: credentials and a router configuration a Zenoh router accepts and enforces."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from proto import topics
from services.bus.credentials import read_credentials, role_file
from services.bus.router import free_tcp_port
from services.bus.zenoh_transport import ZenohTransport
from services.cli import main as cli_main

REPO = Path(__file__).resolve().parents[2]


def generate(out: Path) -> Path:
    """The secrets directory ``causeway bus-secrets --out out`` writes (the router reads its users there)."""
    assert cli_main(["bus-secrets", "--run", "compose", "--out", str(out), "--users-file",
                     str(out / "secrets" / "router-users"),
                     "--router-config", str(REPO / "deploy" / "zenoh" / "router.json5")]) == 0
    return out / "secrets"


def test_it_writes_private_files_and_extends_the_router_config(tmp_path: Path) -> None:
    secrets = generate(tmp_path / "bus")
    assert secrets.stat().st_mode & 0o777 == 0o700
    assert len(list(secrets.iterdir())) == 11 and all(f.stat().st_mode & 0o777 == 0o600 for f in secrets.iterdir())
    config = json.loads((secrets / "router.json5").read_text())
    assert config["mode"] == "router" and config["access_control"]["default_permission"] == "deny"
    assert config["transport"]["auth"]["usrpwd"]["dictionary_file"] == str(secrets / "router-users")
    assert "causeway/*/graph/*" in json.dumps(config["access_control"])  # the dashboard reads every run
    assert read_credentials(role_file(tmp_path / "bus", "operator")).user == "operator"


@pytest.mark.integration
def test_a_router_started_from_it_admits_roles_only(tmp_path: Path) -> None:
    out = generate(tmp_path / "bus")
    config = zenoh.Config.from_file(str(out / "router.json5"))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("plugins", "{}")
    config.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(config)
    try:
        with pytest.raises(zenoh.ZError):
            ZenohTransport(endpoint).close()
        received: list[bytes] = []
        with ZenohTransport(endpoint, read_credentials(out / "supervisor.credentials")) as supervisor, \
                ZenohTransport(endpoint, read_credentials(out / "operator.credentials")) as operator:
            supervisor.subscribe(topics.control("compose", "all"), lambda k, p: received.append(p))
            deadline_tries = 300
            while not received and deadline_tries:
                operator.publish(topics.control("compose", "all"), b"stop")
                deadline_tries -= 1
                supervisor.query(topics.env_spec("compose"), timeout=0.1)  # a pause without sleeping blind
            assert received
    finally:
        router.close()


def test_compose_mode_keeps_the_directory_private_and_the_files_readable_in_containers(tmp_path: Path) -> None:
    """Compose bind-mounts a secret with its host mode; the directory is what keeps it private."""
    out = tmp_path / "bus"
    assert cli_main(["bus-secrets", "--run", "compose", "--out", str(out), "--file-mode", "644"]) == 0
    secrets = out / "secrets"
    assert secrets.stat().st_mode & 0o777 == 0o700
    assert {f.stat().st_mode & 0o777 for f in secrets.iterdir()} == {0o644}
    for writable in ("666", "755", "600x"):
        with pytest.raises(SystemExit) as refused:
            cli_main(["bus-secrets", "--run", "compose", "--out", str(tmp_path / writable), "--file-mode", writable])
        assert refused.value.code == 2 and not (tmp_path / writable).exists()


@pytest.mark.integration
def test_the_routers_own_admin_space_still_answers_its_local_session(tmp_path: Path) -> None:
    """The compose router's healthcheck asks zenohd's REST plugin, which queries the admin space through
    a session inside the router, not a client link: the access control (deny by default) does not
    apply to it. Checked with the router's own session, the same kind of session."""
    out = generate(tmp_path / "bus")
    config = zenoh.Config.from_file(str(out / "router.json5"))
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_tcp_port()}"]))
    config.insert_json5("plugins", "{}")
    config.insert_json5("adminspace/enabled", "true")  # zenohd turns it on whatever the file says
    with zenoh.open(config) as router:
        replies = [str(r.ok.key_expr) for r in router.get("@/*/router", timeout=5) if r.ok is not None]
        assert replies == [f"@/{router.zid()}/router"]
