"""Commands a plugin adds to ``rosgate``: ``rosgate <verb>`` beside run, check, plugins, keygen
and pubkey (the zenoh plugin's ``rosgate router`` is one), registered through the
``rosgate_commands`` hook as a :class:`Command` (an example: docs/plugins.md, "Commands").

``run`` gets the parsed arguments and returns the exit status. A problem the user can fix is
raised as :class:`rosgate.RosgateError` (``ConfigError``, ``LinkError``...): ``rosgate`` prints it
as one message and exits with status 2, as it does for its own commands. A command that runs until
stopped waits with :func:`wait_for_signal`.
"""

from __future__ import annotations

import argparse
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass


def _no_arguments(parser: argparse.ArgumentParser) -> None:
    """A command that takes no arguments adds none."""


@dataclass(frozen=True)
class Command:
    """One ``rosgate <name>`` verb."""

    #: the verb, a short lower-case word (``router``)
    name: str
    #: one line for ``rosgate --help``
    help: str
    #: runs the command with the parsed arguments; returns the exit status
    run: Callable[[argparse.Namespace], int]
    #: adds the command's arguments to its own ``argparse`` parser
    arguments: Callable[[argparse.ArgumentParser], None] = _no_arguments


#: rosgate's own verbs: a plugin cannot take them
CORE_COMMANDS = ("run", "check", "plugins", "keygen", "pubkey")


def command_problem(command: object) -> str | None:
    """Why ``command`` cannot be registered, or None."""
    if not isinstance(command, Command):
        return f"registered {command!r}, which is not a rosgate.Command"
    name = command.name
    if not (isinstance(name, str) and name.replace("-", "_").isidentifier()
            and name == name.lower()):
        return f"command name {name!r} is not a lower-case word (e.g. 'router')"
    if name in CORE_COMMANDS:
        return f"command {name!r} is rosgate's own; skipped"
    if not callable(command.run) or not callable(command.arguments):
        return f"command {name!r}: run and arguments must be functions"
    return None


class Signals:
    """The signals a command that runs until stopped has caught, oldest first.

    The handler only appends to a list. A handler that took a lock (``Event.set`` does) could
    hang for good: Python runs it in the main thread between two bytecodes, possibly while that
    thread holds the very lock inside ``Event.wait`` (seen: two SIGINTs, a bridge that never
    stopped)."""

    def __init__(self, *signums: int):
        self.caught: list[int] = []
        for signum in signums:
            signal.signal(signum, self._caught)

    def _caught(self, signum: int, frame: object) -> None:
        self.caught.append(signum)


def stop_on_signals(*more: int) -> Signals:
    """SIGINT, SIGTERM (and ``more``), caught: what a command that runs until stopped waits on
    with :func:`wait_for_signal`."""
    return Signals(signal.SIGINT, signal.SIGTERM, *more)


def wait_for_signal(signals: Signals) -> int:
    """Wait until a signal is caught; return it. In slices: Python runs handlers in the main
    thread, and a process-directed signal that the kernel hands to another thread (zenoh's and
    DDS's native threads are candidates) does not interrupt a wait without a timeout, so the
    main thread would never run the handler."""
    while not signals.caught:
        time.sleep(0.2)
    return signals.caught.pop(0)
