"""Asking a running bridge for its status, on this machine: its local socket
(:mod:`rosgate.runtime` says where it is and what it answers). ``rosgate top`` reads through
this, and so can a script::

    from rosgate_top.client import StatusClient

    with StatusClient("robot1") as bridge:
        print(bridge.status()["entries"])
"""

from __future__ import annotations

import json
import os
import socket
import stat
import struct
from pathlib import Path
from typing import Any

from rosgate import RUNTIME_VARIABLE, RosgateError, runtime_dir, socket_path
from rosgate import SOCKET_SUFFIX as SUFFIX


class NoBridge(RosgateError):
    """No bridge answers where one was looked for."""


class NotOurs(RosgateError):
    """A status socket (or its folder) that another user made: what it says could be anything."""


def check_owner(path: Path) -> None:
    """:class:`NotOurs` unless ``path``'s folder is this user's and closed to others, and the
    socket is this user's: another local user who made them first could show anything."""
    uid = os.getuid()
    fix = (f"remove it (as its owner or root) and restart the bridge, or set {RUNTIME_VARIABLE} "
           "to a folder of yours")
    for where, info in (("folder", path.parent.stat()), ("socket", path.lstat())):
        if info.st_uid != uid:
            raise NotOurs(f"the status {where} {path if where == 'socket' else path.parent} "
                          f"belongs to uid {info.st_uid}, not to you (uid {uid}): not reading "
                          f"it\n  fix: {fix}")
    mode = path.parent.stat().st_mode
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise NotOurs(f"the status folder {path.parent} may be written by others (mode "
                      f"{stat.S_IMODE(mode):o}): not reading it\n  fix: {fix}")
    if not stat.S_ISSOCK(path.lstat().st_mode):
        raise NotOurs(f"{path} is not a socket: not reading it\n  fix: {fix}")


def _check_peer(sock: socket.socket, path: Path) -> None:
    """:class:`NotOurs` unless the process serving ``sock`` runs as this user (or root)."""
    try:
        _, peer, _ = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                         12))
    except (OSError, AttributeError):  # no SO_PEERCRED here: the owner checks stand alone
        return
    if peer not in (os.getuid(), 0):
        raise NotOurs(f"the process serving {path} runs as uid {peer}, not as you: not reading "
                      "it")


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
            check_owner(self.path)
            self._sock.connect(str(self.path))
            _check_peer(self._sock, self.path)
        except OSError as exc:
            self._sock.close()
            others = [n for n in running() if n != name]
            hint = f" (sockets here: {', '.join(others)})" if others else ""
            raise NoBridge(f"no bridge named {name!r} is running on this machine for this user: "
                           f"{self.path}: {exc.strerror or exc}{hint}") from None
        except NotOurs:
            self._sock.close()
            raise
        self._replies = self._sock.makefile("rb")

    def status(self) -> dict[str, Any]:
        try:
            self._sock.sendall(b'{"get":"status"}\n')
            line = self._replies.readline()
        except OSError as exc:
            raise NoBridge(f"bridge {self.name!r} stopped answering: {exc}") from None
        if not line:
            raise NoBridge(f"bridge {self.name!r} has stopped")
        try:
            status = json.loads(line)
        except ValueError:
            status = None
        if not isinstance(status, dict):
            raise NoBridge(f"bridge {self.name!r} answered something that is no status")
        return status

    def close(self) -> None:
        self._replies.close()
        self._sock.close()

    def __enter__(self) -> StatusClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
