"""Identities: the X25519 key pairs that authenticate a bridge in a session's handshake.

A key file holds 32 bytes in base64 on one line, mode 0600; a public key is written the same way
(44 characters). As with SSH and WireGuard each side lists the public keys it trusts, no
certificate authority. A private key file others can read is refused: they could be this bridge.
"""

from __future__ import annotations

import base64
import os
import stat
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey

KEY_SIZE = 32


class IdentityError(ValueError):
    """A key file or public key that cannot be used; the message says why (never the key)."""

    def __init__(self, message: str, fix: str):
        super().__init__(message)
        self.fix = fix


def generate() -> bytes:
    """A new private key (32 bytes)."""
    return X25519PrivateKey.generate().private_bytes_raw()


def public_of(private: bytes) -> bytes:
    return X25519PrivateKey.from_private_bytes(private).public_key().public_bytes_raw()


def encode(key: bytes) -> str:
    return base64.b64encode(key).decode()


def decode_public(text: object) -> bytes:
    """A public key as written in a bringup.yaml; :class:`IdentityError` if it is not one."""
    key = _decode(text)
    if key is None:
        raise IdentityError("is not a public key (32 bytes in base64, 44 characters)",
                            "paste the public key 'rosgate keygen identity' printed for that "
                            "side (or 'rosgate pubkey FILE')")
    return key


def load_private(path: Path) -> bytes:
    """The private key in ``path``: refused when others can read the file, or it is no key."""
    create = f"create one with 'rosgate keygen identity --out {path}'"
    try:
        mode = path.stat().st_mode
        text = path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) else "not base64 text"
        raise IdentityError(f"cannot read identity file {str(path)!r}: {why}", create) from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise IdentityError(f"identity file {str(path)!r} can be read by other users "
                            f"(mode {stat.S_IMODE(mode):o})", f"chmod 600 {path}")
    key = _decode(text)
    if key is None:
        raise IdentityError(f"{str(path)!r} is not an identity key (32 bytes in base64)", create)
    return key


def write_private(path: Path, key: bytes, force: bool = False) -> None:
    """Write an identity key file (:func:`write_secret`)."""
    write_secret(path, (encode(key) + "\n").encode(), force)


def write_secret(path: Path, data: bytes, force: bool = False) -> None:
    """Write a key file, mode 0600 from its creation (never readable by others, not even
    briefly); never over an existing file unless ``force``."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if force else os.O_EXCL), 0o600)
    with os.fdopen(fd, "wb") as out:
        os.fchmod(out.fileno(), 0o600)
        out.write(data)


def _decode(text: object) -> bytes | None:
    if not isinstance(text, str):
        return None
    try:
        key = base64.b64decode(text.strip(), validate=True)
    except ValueError:  # binascii.Error is one
        return None
    return key if len(key) == KEY_SIZE else None
