"""Commands a plugin adds to ``rosgate`` (the zenoh plugin's ``rosgate router``), registered
through the ``rosgate_commands`` hook as a :class:`Command` (docs/plugins.md, "Commands").

A problem the user can fix is raised as :class:`rosgate.RosgateError`: ``rosgate`` prints it as
one message and exits with status 2. A command that runs until stopped waits with
:func:`wait_for_signal`.
"""

from __future__ import annotations

import argparse
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass


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
    arguments: Callable[[argparse.ArgumentParser], None] = lambda parser: None


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


def stop_on_signals(*more: int) -> list[int]:
    """SIGINT, SIGTERM (and ``more``) caught into a list, oldest first, for
    :func:`wait_for_signal`. The handler only appends: one that took a lock (``Event.set`` does)
    could hang for good, run between two bytecodes of the main thread while it holds that very
    lock in ``Event.wait`` (seen: two SIGINTs, a bridge that never stopped)."""
    caught: list[int] = []
    for signum in (signal.SIGINT, signal.SIGTERM, *more):
        signal.signal(signum, lambda signum, frame: caught.append(signum))
    return caught


def wait_for_signal(caught: list[int]) -> int:
    """Wait until a signal is caught; return it. In slices: a signal the kernel hands to another
    thread (zenoh's, DDS's) does not interrupt a wait without a timeout, and Python runs handlers
    in the main thread only."""
    while not caught:
        time.sleep(0.2)
    return caught.pop(0)
