"""A router on a ``tls/`` endpoint (links that leave a host), with roles: clients verify its certificate
against the CA and authenticate; without the CA, or without credentials, they are refused."""
from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest
import zenoh

from proto import topics
from services.bus.credentials import RouterTls, read_credentials, role_file, write_run_secrets
from services.bus.roles import access_control, new_passwords, run_roles
from services.bus.router import free_tcp_port, start_router
from services.bus.zenoh_transport import ZenohTransport

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl makes the test certificates")]
RUN = "tls"


def certificates(directory: Path) -> tuple[RouterTls, Path]:
    """A throw-away CA and a router certificate it signed for localhost (openssl, 2 days)."""
    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=directory, check=True, capture_output=True)

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
            "-subj", "/CN=causeway-test-ca")
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "router.key", "-out", "router.csr", "-subj", "/CN=localhost")
    (directory / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    openssl("x509", "-req", "-in", "router.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", "router.pem", "-days", "2", "-extfile", "ext.cnf")
    return RouterTls(directory / "router.pem", directory / "router.key"), directory / "ca.pem"


def test_a_tls_router_with_roles(tmp_path: Path) -> None:
    tls, ca = certificates(tmp_path)
    auth = write_run_secrets(tmp_path, new_passwords(), access_control(run_roles(RUN, "cdl")))
    endpoint = f"tls/localhost:{free_tcp_port()}"
    router = start_router(endpoint, auth, tls)
    try:
        for credentials, root_ca in ((read_credentials(role_file(tmp_path, "operator")), ""), (None, str(ca))):
            with pytest.raises(zenoh.ZError):
                ZenohTransport(endpoint, credentials, root_ca).close()
        received: list[bytes] = []
        with ZenohTransport(endpoint, read_credentials(role_file(tmp_path, "supervisor")), str(ca)) as supervisor, \
                ZenohTransport(endpoint, read_credentials(role_file(tmp_path, "operator")), str(ca)) as operator:
            supervisor.subscribe(topics.control(RUN, "all"), lambda k, p: received.append(p))
            deadline = time.monotonic() + 30
            while not received and time.monotonic() < deadline:
                operator.publish(topics.control(RUN, "all"), b"stop")
                time.sleep(0.1)
        assert received and set(received) == {b"stop"}
    finally:
        router.close()


def test_a_certificate_from_bus_secrets_is_verified_by_name(tmp_path: Path) -> None:
    """``causeway bus-secrets --tls-name``'s certificate (services.ops.bus_tls): a client that reaches the
    router by a name the certificate carries gets in; by one it does not carry, it is refused."""
    pytest.importorskip("cryptography")
    from services.ops.bus_tls import write_tls

    files = write_tls(tmp_path, ["localhost"])
    auth = write_run_secrets(tmp_path, new_passwords(), access_control(run_roles(RUN, "cdl")))
    port = free_tcp_port()
    router = start_router(f"tls/localhost:{port}", auth, RouterTls(files.certificate, files.private_key))
    operator = read_credentials(role_file(tmp_path, "operator"))
    try:
        ZenohTransport(f"tls/localhost:{port}", operator, str(files.ca_certificate)).close()
        with pytest.raises(zenoh.ZError):
            ZenohTransport(f"tls/127.0.0.1:{port}", operator, str(files.ca_certificate)).close()
    finally:
        router.close()
