"""Asking a running bridge for its status, on this machine: its local socket
(:mod:`rosgate.runtime` says where it is and what it answers). ``rosgate top`` reads through
this, and so can a script::

    from rosgate_top.client import StatusClient

    with StatusClient("robot1") as bridge:
        print(bridge.status()["entries"])
"""

from __future__ import annotations

import json
import socket
from typing import Any

from rosgate import SOCKET_SUFFIX as SUFFIX
from rosgate import RosgateError, runtime_dir, socket_path


class NoBridge(RosgateError):
    """No bridge answers where one was looked for."""


def running() -> list[str]:
    """The names of the bridges that have a socket here (some may have died since)."""
    folder = runtime_dir()
    try:
        return sorted(p.name[:-len(SUFFIX)] for p in folder.iterdir() if p.name.endswith(SUFFIX))
    except OSError:
        return []


class StatusClient:
    """A connection to one bridge's status socket."""

    def __init__(self, name: str, timeout: float = 5.0):
        self.name = name
        self.path = socket_path(name)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout)
        try:
            self._sock.connect(str(self.path))
        except OSError as exc:
            self._sock.close()
            others = [n for n in running() if n != name]
            hint = f" (sockets here: {', '.join(others)})" if others else ""
            raise NoBridge(f"no bridge named {name!r} is running on this machine for this user: "
                           f"{self.path}: {exc.strerror or exc}{hint}") from None
        self._replies = self._sock.makefile("rb")

    def status(self) -> dict[str, Any]:
        try:
            self._sock.sendall(b'{"get":"status"}\n')
            line = self._replies.readline()
        except OSError as exc:
            raise NoBridge(f"bridge {self.name!r} stopped answering: {exc}") from None
        if not line:
            raise NoBridge(f"bridge {self.name!r} has stopped")
        status: dict[str, Any] = json.loads(line)
        return status

    def close(self) -> None:
        self._replies.close()
        self._sock.close()

    def __enter__(self) -> StatusClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
