"""Errors a user sees. Each carries enough to say what is wrong and how to fix it, without a
traceback."""

from __future__ import annotations


class RosgateError(Exception):
    """Base of every error rosgate reports to a user (the CLI prints it and exits non-zero)."""


class OptionError(RosgateError):
    """A plugin's option is wrong. Raised by :func:`rosgate.options.parse` for what the plugin's
    ``Options`` declare, by an ``Options.__post_init__`` for rules that tie options together, and
    by a plugin's constructor for what only it can tell (a key file that cannot be read).

    ``key`` is the option's name (``key_file``), or ``None`` for the table as a whole (exactly
    one of two options); the core adds the file and line where it was set. ``fix`` says what to do.
    The message never contains a key.
    """

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
    """A link could not be set up (address in use, unreachable, unsupported on this machine).
    Raised by a transport's ``bind`` or ``listen``; the core shows it at the key that named the
    address, without a traceback.

    ``fix`` says what to do about it when the transport knows better than the core's default
    (free the port, or pick another one): a CAN interface that is down, a missing driver.
    """

    def __init__(self, message: str, fix: str | None = None):
        super().__init__(message)
        self.fix = fix


class CodecError(Exception):
    """Bytes or a message a codec cannot handle. Raised per message: the frame is dropped and
    counted."""


class CipherError(Exception):
    """A frame that fails authentication (tampered, foreign, wrong key). Dropped and counted."""
