"""A bridge's folders on this machine: its status (:mod:`rosgate.status`) on a Unix socket,
``<runtime dir>/<name>.sock``, for ``rosgate top``; and what it keeps across restarts in its
state folder (:func:`state_dir`). Each folder is made 0700, and refused when another user owns
it or others may enter it (:class:`NotPrivate`): a bridge never runs on a folder another local
user prepared. The socket is 0600, and a connection from another user (root aside) is closed
unanswered. Never on a network. JSON lines: one request line (``{"get": "status"}``), one
answer line, the status; again on the same connection if the client likes.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import stat
import struct
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .errors import RosgateError

log = logging.getLogger("rosgate")

RUNTIME_VARIABLE = "ROSGATE_RUNTIME_DIR"
STATE_VARIABLE = "ROSGATE_STATE_DIR"
SUFFIX = ".sock"
MAX_REQUEST = 4096  # bytes of one request line; a longer one ends the connection
MAX_CLIENTS = 8  # connections served at once; more wait in the listen backlog


def runtime_dir() -> Path:
    """``$ROSGATE_RUNTIME_DIR``, else ``$XDG_RUNTIME_DIR/rosgate``, else ``/tmp/rosgate-<uid>``."""
    if given := os.environ.get(RUNTIME_VARIABLE):
        return Path(given)
    if (xdg := os.environ.get("XDG_RUNTIME_DIR")) and Path(xdg).is_dir():
        return Path(xdg) / "rosgate"
    return Path(f"/tmp/rosgate-{os.getuid()}")


def socket_path(name: str) -> Path:
    """Where the bridge called ``name`` serves its status (to ``rosgate top``): a Unix socket in
    :func:`runtime_dir`."""
    return runtime_dir() / f"{name}{SUFFIX}"


def state_dir() -> Path:
    """``$ROSGATE_STATE_DIR``, else ``$XDG_STATE_HOME/rosgate``, else ``~/.local/state/rosgate``."""
    if given := os.environ.get(STATE_VARIABLE):
        return Path(given)
    if xdg := os.environ.get("XDG_STATE_HOME"):
        return Path(xdg) / "rosgate"
    return Path.home() / ".local" / "state" / "rosgate"


class NotPrivate(RosgateError):
    """A bridge's folder that another user owns, or that others may enter."""


def private_folder(folder: Path, variable: str) -> Path:
    """``folder``, made 0700 when missing; :class:`NotPrivate` when it is another user's or
    open to others (whoever made it could read, replace or fake what the bridge keeps there),
    naming the folder, its owner and mode, and the fix (``variable`` moves it)."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = folder.stat()
    if info.st_uid != os.getuid() or info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        whose = (f"another user's (uid {info.st_uid})" if info.st_uid != os.getuid()
                 else "open to others")
        raise NotPrivate(f"{folder} is {whose}, mode {stat.S_IMODE(info.st_mode):o}: whoever "
                         "made it could fake this bridge's status or state; the bridge does "
                         "not run on it\n  fix: remove that folder (as its owner or root), or "
                         f"point {variable} at a folder of yours (mode 700)")
    return folder


class StatusServer:
    """Serves ``status()`` on the bridge's socket until :meth:`close`."""

    def __init__(self, name: str, status: Callable[[], dict[str, Any]]):
        self.path = socket_path(name)
        self.status = status
        self._slots = threading.BoundedSemaphore(MAX_CLIENTS)
        self._closed = threading.Event()
        private_folder(self.path.parent, RUNTIME_VARIABLE)
        if self.path.exists() or self.path.is_symlink():
            if _answers(self.path):
                raise OSError(f"another bridge named {name!r} serves {self.path}")
            self.path.unlink()  # left behind by a bridge that died
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)  # the socket is 0600 from its first moment
        try:
            self._sock.bind(str(self.path))
        finally:
            os.umask(old)
        self._sock.listen(MAX_CLIENTS)
        threading.Thread(target=self._accept, name="status-socket", daemon=True).start()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return  # closed
            if not _same_user(conn):
                conn.close()
                continue
            self._slots.acquire()
            threading.Thread(target=self._serve, args=(conn,), name="status-client",
                             daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            with conn, conn.makefile("rb") as requests:
                while not self._closed.is_set():
                    line = requests.readline(MAX_REQUEST)
                    if not line.endswith(b"\n"):
                        return  # closed, or a request too long to be ours
                    conn.sendall(json.dumps(self.status(), separators=(",", ":")).encode()
                                 + b"\n")
        except OSError:
            pass  # the client went away
        except Exception:  # a bug in the status must not end the bridge
            log.exception("status socket: could not answer")
        finally:
            self._slots.release()

    def close(self) -> None:
        self._closed.set()
        self._sock.close()
        with contextlib.suppress(OSError):
            self.path.unlink()


def _same_user(conn: socket.socket) -> bool:
    uid = os.getuid()
    try:
        _, peer_uid, _ = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET,
                                                             socket.SO_PEERCRED, 12))
    except (OSError, AttributeError):  # no SO_PEERCRED here: the 0600 socket is the guard
        return True
    return peer_uid in (uid, 0)


def _answers(path: Path) -> bool:
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.settimeout(1.0)
            probe.connect(str(path))
        return True
    except OSError:
        return False
