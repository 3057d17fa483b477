"""Secrets of the secured bus: a private CA and the router's TLS certificate (with ``cryptography``), and the
user/password dictionary of the router with one password file per credential.

The router proves who it is with a server certificate for the names clients dial (``zenoh`` inside
docker-compose, the host's name or address for edge devices); clients trust only the CA that signed it. Who a
client is, is decided by its user/password (``transport/auth/usrpwd``), not by a client certificate.
Keys are ECDSA P-256 in PKCS#8 PEM: what rustls (Zenoh's TLS) loads.
"""
from __future__ import annotations

import datetime as dt
import ipaddress
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from .acl import edge_user
from .errors import ConfigError

SERVICE_USER = "kmvipe-service"
"""The credential of features, ba and mapstore (deploy/zenoh/router.json5 gives it the pipeline's topics and the
sources' announcements)."""
GATEWAY_USER = "kmvipe-gateway"
"""The credential of query_api: the only one allowed to query the map."""
USERS_FILE = "users.txt"
"""The router's dictionary (``transport/auth/usrpwd/dictionary_file``): one ``user:password`` per line."""

DEFAULT_HOSTS = ("zenoh", "localhost", "127.0.0.1")
"""Names the router certificate is valid for by default: the compose service name and loopback."""
CA_DAYS = 3650
"""CA lifetime: every client holds the CA, so replacing it means visiting every device."""
CERT_DAYS = 825
"""Router certificate lifetime; only the router holds it, so it is the one to renew."""

KeyAndCert = tuple[ec.EllipticCurvePrivateKey, x509.Certificate]


@dataclass(frozen=True)
class BusCerts:
    """Paths of one generated set (all PEM)."""

    ca_cert: Path
    ca_key: Path
    router_cert: Path
    router_key: Path


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "KM-ViPE"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _builder(subject: str, issuer: x509.Name, key: ec.EllipticCurvePrivateKey, days: int) -> x509.CertificateBuilder:
    now = dt.datetime.now(dt.timezone.utc)
    return (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(issuer)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))  # tolerate clocks a little behind
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False))


def make_ca(common_name: str = "kmvipe-bus-ca", days: int = CA_DAYS) -> KeyAndCert:
    """A self-signed CA that may sign leaf certificates only (path length 0)."""
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (_builder(common_name, _name(common_name), key, days)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    return key, cert


def make_leaf(ca_key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate, common_name: str,
              hosts: tuple[str, ...] = (), days: int = CERT_DAYS) -> KeyAndCert:
    """A certificate signed by the CA, valid for ``hosts`` (DNS names or IP addresses) as subject alternative
    names — TLS clients check those, not the common name."""
    key = ec.generate_private_key(ec.SECP256R1())
    sans = [_san(h) for h in hosts]
    builder = (_builder(common_name, ca_cert.subject, key, days)
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                              critical=False)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False))
    if sans:
        builder = builder.add_extension(x509.SubjectAlternativeName(sans), critical=False)
    return key, builder.sign(ca_key, hashes.SHA256())


def _san(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def write_secret(path: Path, data: bytes) -> Path:
    """Write ``data`` readable by its owner only (keys, passwords)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)  # an existing file keeps its old mode through os.open
    return path


def write_bus_certs(out: Path, hosts: tuple[str, ...] = DEFAULT_HOSTS, new_ca: bool = False) -> BusCerts:
    """Write a router certificate for ``hosts`` under ``out`` (``router.pem``, ``router.key``), signed by the CA
    there (``ca.pem``: give it to every client; ``ca.key``: keep it offline), which is made first if absent or
    if ``new_ca``. Keeping the CA lets a router certificate be renewed or get new hosts without touching clients."""
    paths = BusCerts(out / "ca.pem", out / "ca.key", out / "router.pem", out / "router.key")
    if not hosts:
        raise ConfigError("the router certificate needs at least one host name or address (--hosts)")
    if new_ca or not paths.ca_key.exists():
        ca_key, ca_cert = make_ca()
        write_secret(paths.ca_key, key_pem(ca_key))
        paths.ca_cert.write_bytes(cert_pem(ca_cert))
    else:
        ca_key = serialization.load_pem_private_key(paths.ca_key.read_bytes(), password=None)
        ca_cert = x509.load_pem_x509_certificate(paths.ca_cert.read_bytes())
    router_key, router_cert = make_leaf(ca_key, ca_cert, hosts[0], tuple(hosts))
    write_secret(paths.router_key, key_pem(router_key))
    paths.router_cert.write_bytes(cert_pem(router_cert))
    return paths


def write_bus_users(out: Path, streams: tuple[str, ...] = ()) -> dict[str, Path]:
    """Add the service, gateway and one edge credential per stream to ``out/users.txt`` and write each password
    to ``out/<user>.password``. Users already in the dictionary keep their password, so adding a camera does not
    lock out the others. Returns ``{user: password file}``."""
    users_file = out / USERS_FILE
    known = dict(line.split(":", 1) for line in users_file.read_text().splitlines() if ":" in line) \
        if users_file.exists() else {}
    for user in (SERVICE_USER, GATEWAY_USER, *map(edge_user, streams)):
        known.setdefault(user, secrets.token_urlsafe(24))  # [A-Za-z0-9_-]: never the dictionary's ':'
    write_secret(users_file, "".join(f"{u}:{p}\n" for u, p in known.items()).encode())
    return {u: write_secret(out / f"{u}.password", p.encode()) for u, p in known.items()}
