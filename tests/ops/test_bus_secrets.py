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
    assert len(list(secrets.iterdir())) == 12 and all(f.stat().st_mode & 0o777 == 0o600 for f in secrets.iterdir())
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
        with pytest.raises(zenoh.ZError):  # written for kustomize without --extractor, admitted only with it
            ZenohTransport(endpoint, read_credentials(out / "factor-extractor.credentials")).close()
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


TLS_K8S = ["--listen", "tls/[::]:7447", "--tls-name", "router", "--tls-name", "router.causeway.svc",
           "--tls-name", "10.0.0.7"]


def test_tls_names_make_a_ca_and_a_router_certificate_the_router_config_reads(tmp_path: Path) -> None:
    from cryptography import x509

    from services.bus.router import ROUTER_COMMON_NAME

    out = tmp_path / "bus"
    assert cli_main(["bus-secrets", "--run", "k8s", "--out", str(out), "--users-file", "/etc/zenoh/router-users",
                     "--file-mode", "644", *TLS_K8S]) == 0
    secrets = out / "secrets"
    modes = {f.name: f.stat().st_mode & 0o777 for f in secrets.iterdir()}
    assert modes.pop("bus-ca.key") == 0o600 and set(modes.values()) == {0o644}, "the CA's key stays private"
    ca = x509.load_pem_x509_certificate((secrets / "bus-ca.pem").read_bytes())
    router = x509.load_pem_x509_certificate((secrets / "router-tls.pem").read_bytes())
    router.verify_directly_issued_by(ca)
    names = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert names.get_values_for_type(x509.DNSName) == ["router", "router.causeway.svc"]
    assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ["10.0.0.7"]
    assert router.subject.rfc4514_string() == f"CN={ROUTER_COMMON_NAME}"
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    config = json.loads((secrets / "router.json5").read_text())
    assert config["listen"]["endpoints"] == ["tls/[::]:7447"]
    assert config["transport"]["link"]["tls"]["listen_certificate"] == "/etc/zenoh/router-tls.pem"
    assert config["transport"]["link"]["tls"]["listen_private_key"] == "/etc/zenoh/router-tls.key"
    assert "BEGIN CERTIFICATE" in (secrets / "router-roots.pem").read_text()


def test_mesh_users_and_joins_extend_the_access_control_to_the_run_only(tmp_path: Path) -> None:
    first = tmp_path / "first"
    assert cli_main(["bus-secrets", "--run", "mesh", "--out", str(first), *TLS_K8S, "--mesh-user", "router-b"]) == 0
    joined = json.loads((first / "secrets" / "access-control.json").read_text())
    assert {"id": "meshed-router-users", "usernames": ["router-b"]} in joined["subjects"]
    rule = next(r for r in joined["rules"] if r["id"] == "meshed-routers")
    assert rule["key_exprs"] == ["causeway/mesh/**"] and set(rule["flows"]) == {"ingress", "egress"}
    assert read_credentials(first / "secrets" / "router-b.credentials").user == "router-b"
    second = tmp_path / "second"
    assert cli_main(["bus-secrets", "--run", "mesh", "--out", str(second), "--join", "tls/first.example:7447",
                     "--join-credentials", str(first / "secrets" / "router-b.credentials"),
                     "--join-ca", str(first / "secrets" / "bus-ca.pem")]) == 0
    config = json.loads((second / "secrets" / "router.json5").read_text())
    assert config["connect"]["endpoints"] == ["tls/first.example:7447"]
    assert config["transport"]["auth"]["usrpwd"]["user"] == "router-b"
    assert (second / "secrets" / "router-roots.pem").read_text() == (first / "secrets" / "bus-ca.pem").read_text()
    assert {"id": "meshed-router-certificates", "cert_common_names": ["causeway-router"]} in \
        json.loads((second / "secrets" / "access-control.json").read_text())["subjects"]
    assert config["access_control"]["enabled"] and len(config["access_control"]["policies"]) == 9


@pytest.mark.parametrize("args, says", [
    (["--listen", "tls/[::]:7447"], "has no certificate"),
    (["--tls-name", "router"], "listens on none"),
    (["--listen", "tls/[::]:7447", "--tls-name", "bad name"], "expected a DNS name"),
    (["--mesh-user", "env-worker"], "not a role"),
    (["--join", "tcp/first:7447", "--join-credentials", "x", "--join-ca", "y"], "use tls/"),
    (["--join", "tls/first:7447"], "--join needs --join-credentials"),
])
def test_it_refuses_a_router_that_could_not_start_or_would_link_in_clear(tmp_path: Path, capsys, args: list[str],
                                                                         says: str) -> None:
    with pytest.raises(SystemExit) as refused:
        cli_main(["bus-secrets", "--run", "mesh", "--out", str(tmp_path / "out"), *args])
    assert refused.value.code == 2 and says in capsys.readouterr().err


@pytest.mark.parametrize("extractor, worker_publishes, extractor_publishes", [
    ("frames", "causeway/compose/frames/*", "causeway/compose/transitions/*"),
    ("latent", "causeway/compose/frames/*", "causeway/compose/latent/*"),
])
def test_an_extractor_adds_its_role_and_changes_the_workers(tmp_path: Path, extractor: str, worker_publishes: str,
                                                           extractor_publishes: str) -> None:
    """``--extractor frames|latent``: the factor-extractor's credentials and rules, as a local run with
    ``--worker-publish-frames true`` or ``--label-latent-actions true`` draws them. Without it the file is
    still written (a kustomize base generates its Secret from it), for a user the router does not know."""
    plain = generate(tmp_path / "plain")
    unadmitted = read_credentials(plain / "factor-extractor.credentials")
    assert unadmitted.user == "factor-extractor" and f"{unadmitted.user}:" not in (plain / "router-users").read_text()
    assert "factor-extractor" not in (plain / "access-control.json").read_text()
    out = tmp_path / extractor
    assert cli_main(["bus-secrets", "--run", "compose", "--out", str(out), "--extractor", extractor,
                     "--method", "flam" if extractor == "latent" else "cdl"]) == 0
    assert read_credentials(role_file(out, "factor-extractor")).user == "factor-extractor"
    rules = {r["id"]: r["key_exprs"] for r in json.loads((out / "secrets" / "access-control.json").read_text())["rules"]}
    assert worker_publishes in rules["env-worker-ingress-put"]
    assert extractor_publishes in rules["factor-extractor-ingress-put"]
    assert ("causeway/compose/transitions/*" in rules["env-worker-ingress-put"]) == (extractor == "latent")
    with pytest.raises(SystemExit):
        cli_main(["bus-secrets", "--run", "compose", "--out", str(tmp_path / "bad"), "--extractor", "pixels"])
