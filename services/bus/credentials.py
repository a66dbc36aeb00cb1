"""Bus credentials on disk: one file per role and the router's user dictionary, readable by their owner only.

A local run with ``--bus-auth`` keeps them in ``<run_dir>/secrets/`` (directory mode 700, files 600),
drawn afresh each time the run starts:

- ``<role>.credentials``: one line ``<user>:<password>``; a process is given the *path* of its role's
  file (``CAUSEWAY_BUS_CREDENTIALS`` / ``--bus-credentials``), never the password itself;
- ``router-users``: the router's ``transport/auth/usrpwd/dictionary_file`` (every role's line);
- ``access-control.json``: the router's access control, for reading (not secret, but kept together).

Under Compose or Kubernetes the same one-line file is mounted as a secret and named the same way.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SECRETS_DIR = "secrets"
USERS_FILE = "router-users"
ACL_FILE = "access-control.json"


@dataclass(frozen=True)
class Credentials:
    """A Zenoh user and password (``transport/auth/usrpwd``)."""

    user: str
    password: str = ""

    def __repr__(self) -> str:  # never the password in a log line or a traceback
        return f"Credentials(user={self.user!r}, password=<hidden>)"


@dataclass(frozen=True)
class RouterTls:
    """A router's TLS certificate and private key (PEM files), for ``tls/`` endpoints: links that leave
    a host. Clients verify it with the CA certificate that signed it (``bus_tls_root_ca``)."""

    certificate: Path
    private_key: Path


@dataclass(frozen=True)
class RouterAuth:
    """What a router needs to authenticate clients and enforce the roles."""

    users_file: Path
    access_control: dict[str, Any]


def read_credentials(path: str | Path) -> Credentials:
    """The ``user:password`` line of ``path``; ``ValueError`` naming the file when it is not one."""
    try:
        text = Path(path).read_text().strip()
    except OSError as exc:
        raise ValueError(f"cannot read bus credentials {path}: {exc.strerror}") from None
    user, colon, password = text.partition(":")
    if not user or not colon or not password or "\n" in text:
        raise ValueError(f"bus credentials {path}: expected one line user:password")
    return Credentials(user, password)


def role_file(run_dir: str | Path, role: str) -> Path:
    """Where a local run keeps ``role``'s credentials."""
    return Path(run_dir) / SECRETS_DIR / f"{role}.credentials"


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(text)
    os.chmod(path, 0o600)  # an existing file keeps its mode on O_CREAT


def write_role_credentials(run_dir: str | Path, role: str, password: str) -> Path:
    """``role``'s one-line credentials file under ``<run_dir>/secrets``, private to its owner; its path."""
    path = role_file(run_dir, role)
    _write_private(path, f"{role}:{password}\n")
    return path


def write_run_secrets(run_dir: str | Path, passwords: dict[str, str], access_control: dict[str, Any]) -> RouterAuth:
    """Write every role's credentials file, the router's user dictionary and its access control under
    ``<run_dir>/secrets``; returns what the router is started with."""
    directory = Path(run_dir) / SECRETS_DIR
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    for role, password in passwords.items():
        write_role_credentials(run_dir, role, password)
    _write_private(directory / USERS_FILE, "".join(f"{role}:{pw}\n" for role, pw in passwords.items()))
    _write_private(directory / ACL_FILE, json.dumps(access_control, indent=1) + "\n")
    return RouterAuth(directory / USERS_FILE, access_control)
