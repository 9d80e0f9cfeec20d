"""rosgate cipher ``fernet``: Fernet tokens (AES-128-CBC + HMAC-SHA256), as ros2_socket_bridge used.

Kept for compatibility and familiarity; for speed prefer an AEAD cipher (Fernet is ~160 MB/s
on a 1 MiB frame and adds 57+ bytes plus base64 growth of a third).

The envelope header is authenticated by sealing it inside the token with the payload; ``open``
refuses a token whose inner header differs from the one that came in clear.

Options (``plugins: {fernet: {...}}``), exactly one of:

``key_file``  path of a file holding the key (relative to the bringup.yaml). Create one with
              ``rosgate keygen fernet --out secret.key`` (mode 0600).
``key_env``   name of an environment variable holding the key.

The key is never taken from the command line, where other users could read it in ``ps``.
"""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path
from typing import Any, Mapping

from cryptography.fernet import Fernet, InvalidToken

from rosgate import Cipher, CipherError, OptionError, hookimpl


def load_key(options: Mapping[str, Any], base_dir: Path, plugin: str) -> bytes:
    """The key named by ``key_file`` or ``key_env`` (shared convention of rosgate ciphers)."""
    unknown = set(options) - {"key_file", "key_env"}
    if unknown:
        raise OptionError(sorted(unknown)[0], f"unknown option of {plugin}",
                          "valid options are key_file and key_env")
    if ("key_file" in options) == ("key_env" in options):
        raise OptionError(None, f"{plugin} needs exactly one of key_file or key_env",
                          f"create a key with 'rosgate keygen {plugin} --out {plugin}.key' and set "
                          f"plugins: {{{plugin}: {{key_file: {plugin}.key}}}}")
    if "key_env" in options:
        name = options["key_env"]
        value = os.environ.get(str(name))
        if not value:
            raise OptionError("key_env", f"environment variable {name!r} is not set or empty",
                              f"export {name}=<key made by 'rosgate keygen {plugin}'>")
        return value.strip().encode()
    path = base_dir / str(options["key_file"])
    try:
        mode = path.stat().st_mode
        data = path.read_bytes().strip()
    except OSError as exc:
        raise OptionError("key_file", f"cannot read key file {str(path)!r}: {exc.strerror}",
                          f"create it with 'rosgate keygen {plugin} --out {path}'") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        logging.getLogger("rosgate").warning(
            "key file %s is readable by other users; chmod 600 it", path)
    return data


class FernetCipher(Cipher):
    name = "fernet"

    def __init__(self, options: Mapping[str, Any], base_dir: Path):
        super().__init__(options, base_dir)
        key = load_key(options, base_dir, self.name)
        try:
            self._fernet = Fernet(key)
        except (ValueError, TypeError):
            source = "key_file" if "key_file" in options else "key_env"
            where = "file" if source == "key_file" else "variable"
            raise OptionError(source, f"the key in {where} {options[source]!r} is not a Fernet key "
                              "(32 url-safe base64-encoded bytes)",
                              "create one with 'rosgate keygen fernet --out secret.key'") from None

    def seal(self, header: bytes, payload: bytes) -> bytes:
        return self._fernet.encrypt(header + payload)

    def open(self, header: bytes, body: bytes) -> bytes:
        try:
            plain = self._fernet.decrypt(body)
        except (InvalidToken, ValueError, TypeError):
            raise CipherError("not a valid token for this key") from None
        if plain[:len(header)] != header:
            raise CipherError("header does not match the sealed one")
        return plain[len(header):]

    @classmethod
    def generate_key(cls) -> bytes:
        return Fernet.generate_key()


@hookimpl
def rosgate_ciphers(register):
    register(FernetCipher)
