"""A CA and a router's TLS certificate for ``tls/`` links, the links that leave a host (``causeway
bus-secrets --tls-name NAME ...``).

The CA signs one router certificate whose subject alternative names are the names clients and other
routers reach the router by (DNS names, IP addresses): the Kubernetes Service's names, the compose
service name, a host's address. Clients and joining routers verify it against ``bus-ca.pem``
(``CAUSEWAY_BUS_TLS_ROOT_CA`` / ``transport/link/tls/root_ca_certificate``); Zenoh checks the name
it connected to against the certificate (``verify_name_on_connect``, on by default).

Keys are ECDSA P-256 (rustls, which Zenoh's TLS link uses, takes them), made with the ``cryptography``
package (``pip install 'causeway[deploy]'``) and written as they are made, mode 600, never into the
repository (the output directories are git-ignored) or an image. ``bus-ca.key`` stays 600 whatever
mode the other files get: it is mounted nowhere and only signs.
"""
from __future__ import annotations

import datetime
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from services.bus.router import ROUTER_COMMON_NAME

CA_CERTIFICATE = "bus-ca.pem"
CA_KEY = "bus-ca.key"
ROUTER_CERTIFICATE = "router-tls.pem"
ROUTER_KEY = "router-tls.key"
VALID_DAYS = 365


@dataclass(frozen=True)
class TlsFiles:
    """What ``write_tls`` wrote: the CA certificate (what clients trust) and the router's pair."""

    ca_certificate: Path
    ca_key: Path
    certificate: Path
    private_key: Path


def _cryptography():
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:
        raise ValueError("TLS certificates need the cryptography package: pip install 'causeway[deploy]' "
                         "(make venv installs it)") from None
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def subject_names(names: Sequence[str]) -> list:
    """``x509.GeneralName``s for ``names``: IP addresses as such, everything else a DNS name."""
    x509 = _cryptography()[0]
    general = []
    for name in names:
        try:
            general.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            if not name or any(c in name for c in " /:@") or name.startswith(".") or name.endswith("."):
                raise ValueError(f"--tls-name {name!r}: expected a DNS name or an IP address") from None
            general.append(x509.DNSName(name))
    return general


def _write_private(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(data)
    os.chmod(path, 0o600)


def write_tls(directory: Path, names: Sequence[str], days: int = VALID_DAYS) -> TlsFiles:
    """A fresh CA and a router certificate for ``names`` (its subject alternative names; its common name is
    ``ROUTER_COMMON_NAME``, by which a joining router recognises the far side of its link) in ``directory``."""
    if not names:
        raise ValueError("a router certificate needs at least one name (--tls-name)")
    x509, hashes, serialization, ec, usage_oid, name_oid = _cryptography()
    alternative = x509.SubjectAlternativeName(subject_names(names))
    now = datetime.datetime.now(datetime.timezone.utc)
    start, end = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(name_oid.COMMON_NAME, "causeway bus CA")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
          .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
          .sign(ca_key, hashes.SHA256()))
    key = ec.generate_private_key(ec.SECP256R1())
    router = (x509.CertificateBuilder()
              .subject_name(x509.Name([x509.NameAttribute(name_oid.COMMON_NAME, ROUTER_COMMON_NAME)]))
              .issuer_name(ca_name).public_key(key.public_key()).serial_number(x509.random_serial_number())
              .not_valid_before(start).not_valid_after(end)
              .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
              .add_extension(x509.KeyUsage(True, False, False, False, False, False, False, False, False), critical=True)
              .add_extension(x509.ExtendedKeyUsage([usage_oid.SERVER_AUTH, usage_oid.CLIENT_AUTH]), critical=False)
              .add_extension(alternative, critical=False)
              .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
              .sign(ca_key, hashes.SHA256()))
    pkcs8 = serialization.PrivateFormat.PKCS8
    files = TlsFiles(directory / CA_CERTIFICATE, directory / CA_KEY, directory / ROUTER_CERTIFICATE,
                     directory / ROUTER_KEY)
    _write_private(files.ca_key, ca_key.private_bytes(serialization.Encoding.PEM, pkcs8, serialization.NoEncryption()))
    _write_private(files.private_key, key.private_bytes(serialization.Encoding.PEM, pkcs8, serialization.NoEncryption()))
    _write_private(files.ca_certificate, ca.public_bytes(serialization.Encoding.PEM))
    _write_private(files.certificate, router.public_bytes(serialization.Encoding.PEM))
    return files
