"""Where a cipher's key comes from, the convention every rosgate cipher shares: ``Options =
KeyOptions`` (``key_file`` or ``key_env``, never the key on a command line ``ps`` shows), and
:func:`load_key` for its bytes, stripped of blanks. What they mean is the cipher's business: it
raises ``OptionError(key_source(options), ...)`` when they are no key it can use.
"""

from __future__ import annotations

import logging
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from .errors import OptionError
from .options import option


@dataclass(frozen=True)
class KeyOptions:
    """Exactly one is set: :func:`load_key` checks, since it knows the cipher's name."""

    key_file: str | None = option(
        None, "file holding the key, relative to the bringup.yaml (rosgate keygen NAME --out "
        "FILE); or key_env")
    key_env: str | None = option(None, "environment variable holding the key; or key_file")


def load_key(options: KeyOptions, base_dir: Path, plugin: str) -> bytes:
    """The key named by ``key_file`` or ``key_env``; :class:`OptionError` at the option that is
    missing or unreadable (the message never contains the key)."""
    if (options.key_file is None) == (options.key_env is None):
        raise OptionError(None, f"{plugin} needs exactly one of key_file or key_env",
                          f"create a key with 'rosgate keygen {plugin} --out {plugin}.key' and set "
                          f"plugins: {{{plugin}: {{key_file: {plugin}.key}}}}")
    if options.key_env is not None:
        name = options.key_env
        value = os.environ.get(name)
        if not value:
            raise OptionError("key_env", f"environment variable {name!r} is not set or empty",
                              f"export {name}=<key made by 'rosgate keygen {plugin}'>")
        return value.strip().encode()
    path = base_dir / str(options.key_file)
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


def key_source(options: KeyOptions) -> str:
    """The option the key came from, for an ``OptionError`` about the key's content."""
    return "key_file" if options.key_file is not None else "key_env"


def describe_source(options: KeyOptions) -> str:
    """``file 'secret.key'`` or ``variable 'NAME'``: where a bad key was found, for a message."""
    if options.key_file is not None:
        return f"file {options.key_file!r}"
    return f"variable {options.key_env!r}"


def identity_public_key(path: Path, make: bool = False) -> str:
    """The public key (base64, as files write it) of the identity file at ``path``, which is made
    first (mode 0600) when ``make`` and there is none. A file that cannot be used raises a
    ValueError whose ``fix`` says what to do."""
    from . import identity  # here: its cryptography takes a while to import

    if make and not path.exists():
        identity.write_private(path, identity.generate())
    return identity.encode(identity.public_of(identity.load_private(path)))
