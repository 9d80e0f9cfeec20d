"""Only the fleet: zenoh's own mutual TLS, with certificates ``rosgate certs`` makes, and the
access control ``rosgate router`` enforces with them.

``rosgate certs --out DIR NAME...`` makes (or reuses) a fleet CA in ``DIR/ca.pem`` + ``ca.key``
and, for each name, ``DIR/NAME.pem`` + ``NAME.key``: a certificate whose common name is the
bridge's (or the router's) name, signed by the CA. Keys are written mode 0600.

A bridge with ``plugins: {zenoh: {tls: DIR}}`` presents ``DIR/<its name>.pem`` and accepts only
peers whose certificate the CA signed (``transport.link.tls`` with ``enable_mtls``); its
endpoints are ``tls/<host>:<port>``. The router's access control (:func:`access_control`) names
robots by those common names: each robot may put, serve and hold tokens only on
``<prefix>/<robot>/**``, and may subscribe or query only there; its liveliness token may be
``<prefix>/<robot>/@alive`` or, under each of ``tokens`` (the plugin's default prefix, which a
bridge's token has unless its file sets ``prefix:``), ``<token prefix>/<robot>/@alive``, never
another robot's; a base may do anything; anything else is denied. A robot is told of every
subscription under ``<prefix>/**`` (its key expression, no data): a zenoh publisher sends only
while it knows a matching subscriber, and a base's fleet entry subscribes ``<prefix>/*/<topic>``,
which is no key of the robot's own.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

CA = "ca"
YEARS = 5

#: what a robot may send on its own keys, and what it may take from them (zenoh's ACL messages)
SEND = ["put", "delete", "declare_queryable", "reply", "liveliness_token"]
TAKE = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]


def files(directory: str | Path, name: str) -> tuple[Path, Path]:
    """(certificate, private key) of ``name`` in ``directory``."""
    folder = Path(directory)
    return folder / f"{name}.pem", folder / f"{name}.key"


def zenoh_tls(directory: str | Path, name: str) -> dict[str, Any]:
    """zenoh's ``transport.link.tls`` for ``name``: present its certificate on both sides of
    every link, accept only peers the fleet's CA signed."""
    cert, key = files(directory, name)
    ca, _ = files(directory, CA)
    for path in (ca, cert, key):
        if not path.is_file():
            raise FileNotFoundError(str(path))
    return {"root_ca_certificate": str(ca), "enable_mtls": True,
            "listen_certificate": str(cert), "listen_private_key": str(key),
            "connect_certificate": str(cert), "connect_private_key": str(key),
            "verify_name_on_connect": False}  # the CA and the ACL's common names identify peers


def access_control(prefix: str, robots: list[str], bases: list[str],
                   tokens: Sequence[str] = ()) -> dict[str, Any]:
    """zenoh's ``access_control``: default deny; bases anything; each robot its own keys and
    its own liveliness token under ``prefix`` and under each of ``tokens``."""
    alive = list(dict.fromkeys([prefix, *tokens]))  # zenoh's ** matches no @ chunk: named
    rules: list[dict[str, Any]] = [{"id": "base", "permission": "allow",
                                    "flows": ["ingress", "egress"], "messages": SEND + TAKE,
                                    "key_exprs": ["**", "@/**",
                                                  *(f"{p}/*/@alive" for p in alive)]}]
    subjects: list[dict[str, Any]] = [{"id": "bases", "cert_common_names": bases}] if bases \
        else []
    policies = [{"rules": ["base"], "subjects": ["bases"]}] if bases else []
    if robots:  # the subscriptions a robot's publishers must know of to send at all
        rules.append({"id": "subscriptions", "permission": "allow", "flows": ["egress"],
                      "messages": ["declare_subscriber"], "key_exprs": [f"{prefix}/**"]})
    for robot in robots:
        own = [f"{prefix}/{robot}/**", *(f"{p}/{robot}/@alive" for p in alive)]
        rules.append({"id": f"robot {robot}", "permission": "allow",
                      "flows": ["ingress", "egress"], "messages": SEND + TAKE, "key_exprs": own})
        subjects.append({"id": robot, "cert_common_names": [robot]})
        policies.append({"rules": [f"robot {robot}", "subscriptions"], "subjects": [robot]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def make(directory: str | Path, names: list[str]) -> list[Path]:
    """The CA (made once) and a certificate for each name; the files written."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    folder = Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    ca_cert_path, ca_key_path = files(folder, CA)
    now = datetime.datetime.now(datetime.UTC)
    written: list[Path] = []

    def save(key: Any, cert: Any, name: str) -> None:
        cert_path, key_path = files(folder, name)
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as out:
            out.write(key.private_bytes(serialization.Encoding.PEM,
                                        serialization.PrivateFormat.PKCS8,
                                        serialization.NoEncryption()))
        written.extend([cert_path, key_path])

    def subject(name: str) -> Any:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])

    if ca_cert_path.is_file() and ca_key_path.is_file():
        ca_cert = x509.load_pem_x509_certificate(ca_cert_path.read_bytes())
        ca_key = serialization.load_pem_private_key(ca_key_path.read_bytes(), None)
    else:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_cert = (x509.CertificateBuilder().subject_name(subject("rosgate fleet CA"))
                   .issuer_name(subject("rosgate fleet CA")).public_key(ca_key.public_key())
                   .serial_number(x509.random_serial_number()).not_valid_before(now)
                   .not_valid_after(now + datetime.timedelta(days=365 * YEARS))
                   .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                   .sign(ca_key, hashes.SHA256()))
        save(ca_key, ca_cert, CA)
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        names_alt = x509.SubjectAlternativeName([
            x509.DNSName(name), x509.DNSName("localhost"),
            x509.IPAddress(ipaddress.ip_address("127.0.0.1"))])
        cert = (x509.CertificateBuilder().subject_name(subject(name))
                .issuer_name(ca_cert.subject).public_key(key.public_key())
                .serial_number(x509.random_serial_number()).not_valid_before(now)
                .not_valid_after(now + datetime.timedelta(days=365 * YEARS))
                .add_extension(names_alt, critical=False)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .sign(ca_key, hashes.SHA256()))  # type: ignore[arg-type]
        save(key, cert, name)
    return written
