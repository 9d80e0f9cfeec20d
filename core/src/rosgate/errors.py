"""Errors a user sees. Each carries enough to say what is wrong and how to fix it, without a
traceback."""

from __future__ import annotations


class RosgateError(Exception):
    """Base of every error rosgate reports to a user (the CLI prints it and exits non-zero)."""


class OptionError(RosgateError):
    """A plugin's option is wrong: raised by :func:`rosgate.options.parse`, an
    ``Options.__post_init__`` or a plugin's constructor. ``key`` is the option (``key_file``), or
    ``None`` for the whole table; the core adds file and line. The message never holds a key."""

    def __init__(self, key: str | None, message: str, fix: str | None = None):
        super().__init__(message)
        self.key = key
        self.message = message
        self.fix = fix


class ConfigError(RosgateError):
    """A bringup.yaml problem: names the file, the line, the key and the fix."""

    def __init__(self, message: str, *, file: str | None = None, line: int | None = None,
                 key: str | None = None, fix: str | None = None):
        self.message = message
        self.file = file
        self.line = line
        self.key = key
        self.fix = fix
        super().__init__(str(self))

    def __str__(self) -> str:
        where = (self.file or "<config>") + (f":{self.line}" if self.line is not None else "")
        key = f"{self.key}: " if self.key else ""
        fix = f"\n  fix: {self.fix}" if self.fix else ""
        return f"{where}: {key}{self.message}{fix}"


class LinkError(RosgateError):
    """A link could not be set up (address in use, unreachable, unsupported), raised by a
    transport's ``bind`` or ``listen`` and shown at the key that named the address. ``fix``: when
    the transport knows better than "free the port" (a CAN interface down, a missing driver)."""

    def __init__(self, message: str, fix: str | None = None):
        super().__init__(message)
        self.fix = fix


class CodecError(Exception):
    """Bytes or a message a codec cannot handle: the frame is dropped and counted."""


class CipherError(Exception):
    """A frame that fails authentication (tampered, foreign, wrong key). Dropped and counted."""
