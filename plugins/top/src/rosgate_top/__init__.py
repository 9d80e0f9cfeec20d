"""``rosgate top``: a live terminal view of a bridge running on this machine.

It asks the bridge's local status socket (:mod:`rosgate_top.client`) once a second and draws what
changed as rates (:mod:`rosgate_top.view`) with rich. Keys are read from the terminal one at a
time (cbreak mode: no echo, Ctrl-C still interrupts); without a terminal (a pipe) it draws
until stopped.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import select
import sys
import termios
import time
import tty
from collections.abc import Callable, Iterator
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import yaml

from rosgate import Command, ConfigError, hookimpl

from .client import NoBridge, StatusClient, running

# rich takes a while to import: it (and .view) is imported when `rosgate top` runs, not when the
# plugin loads to add its command; missing, it still makes the plugin fail to load, by name
if find_spec("rich") is None:
    raise ModuleNotFoundError("No module named 'rich'", name="rich")

INTERVAL = 1.0


def arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bridge", nargs="?", metavar="FILE or NAME",
                        help="the bridge's bringup.yaml or its name (default: the only bridge "
                             "running here)")
    parser.add_argument("--interval", type=float, default=INTERVAL, metavar="SECONDS",
                        help=f"seconds between refreshes (default {INTERVAL:g})")
    parser.add_argument("--once", action="store_true",
                        help="print one view (rates over one interval) as text and exit")


def bridge_name(given: str | None) -> str:
    """The bridge a ``FILE or NAME`` argument means."""
    if given is None:
        names = running()
        if len(names) == 1:
            return names[0]
        if not names:
            raise NoBridge("no rosgate bridge is running on this machine for this user (start "
                           "one with rosgate run FILE)")
        raise ConfigError(f"{len(names)} bridges run here: {', '.join(names)}",
                          fix="name one: rosgate top NAME", file="rosgate top")
    path = Path(given)
    if path.suffix in (".yaml", ".yml") or path.is_file():
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
            name = data["bridge"]["name"]
        except (OSError, yaml.YAMLError, TypeError, KeyError) as exc:
            raise ConfigError(f"cannot read the bridge's name from it: {exc}", file=given,
                              fix="give the bridge's name instead: rosgate top NAME") from None
        return str(name)
    return given


#: the columns of ``--once`` when its output is not a terminal: every row whole
NO_WIDTH_LIMIT = 10_000
#: what a status that is not a bridge's (fields missing or of another kind) raises as it is drawn
NOT_A_STATUS = (KeyError, TypeError, ValueError, AttributeError, IndexError)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console  # here, not at the top: see find_spec above

    from .view import render

    name = bridge_name(args.bridge)
    with StatusClient(name) as client:
        before = client.status()
        try:
            if args.once:
                time.sleep(args.interval)
                # into a pipe or a file: the whole width of every row (rich would cut at 80 columns)
                piped = None if sys.stdout.isatty() else NO_WIDTH_LIMIT
                Console(width=piped).print(render(client.status(), before, keys=False))
                return 0
            return _live(client, before, args.interval)
        except NOT_A_STATUS as exc:
            raise NoBridge(f"bridge {name!r} answered something that is no status it knows "
                           f"({type(exc).__name__}: {exc!r:.80})") from None


def _live(client: StatusClient, before: dict[str, Any], interval: float) -> int:
    from rich.console import Console
    from rich.live import Live

    from .view import SORT_KEYS, render

    console = Console()
    sort, reverse = 0, False
    now = before
    try:
        with Live(render(now, None), console=console, auto_refresh=False,
                  redirect_stdout=False, redirect_stderr=False) as live, _keys() as key:
            due = time.monotonic() + interval
            while True:
                pressed = key(max(0.0, due - time.monotonic()))
                if pressed in ("q", "Q"):
                    break
                if pressed == "s":
                    sort = (sort + 1) % len(SORT_KEYS)
                elif pressed == "r":
                    reverse = not reverse
                elif pressed is None:
                    before, now = now, client.status()
                    due = time.monotonic() + interval
                live.update(render(now, before, SORT_KEYS[sort], reverse), refresh=True)
    except KeyboardInterrupt:
        pass
    except NoBridge as exc:
        console.print(f"rosgate top: {exc}")
        return 1
    return 0


@contextlib.contextmanager
def _keys() -> Iterator[Callable[[float], str | None]]:
    """A function that waits up to its argument (seconds) for one key: the key, or None."""
    fd = sys.stdin.fileno() if sys.stdin is not None else -1
    if fd < 0 or not os.isatty(fd):
        def wait(timeout: float) -> str | None:
            time.sleep(timeout)
            return None
        yield wait
        return
    saved = termios.tcgetattr(fd)
    tty.setcbreak(fd)
    try:
        def key(timeout: float) -> str | None:
            ready, _, _ = select.select([fd], [], [], timeout)
            data = os.read(fd, 1) if ready else b""
            if ready and not data:  # the terminal is gone: wait as if no key came
                time.sleep(timeout)
            return data.decode(errors="replace") or None
        yield key
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


@hookimpl
def rosgate_commands(register: Callable[[Command], None]) -> None:
    register(Command("top", "a live view of a running bridge (rates, drops, links)", run,
                     arguments))
