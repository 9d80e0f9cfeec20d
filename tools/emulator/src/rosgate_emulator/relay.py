"""What the UDP and TCP relays share: the lock and the condition their counters change under, their
threads, ``close()`` and ``wait_until()``; and quiet socket helpers."""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable
from typing import Any

from .shaping import Profile

SOCKET_BUFFER = 4 << 20  # the relays' kernel buffers, so the relay itself drops nothing
JOIN_TIMEOUT = 5.0


def family(host: str) -> socket.AddressFamily:
    return socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)[0][0]


def close_quietly(sock: socket.socket | None) -> None:
    if sock is not None:
        try:
            sock.close()
        except OSError:
            pass


def shutdown_quietly(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass


class Relay:
    """What both relays share: the lock, the change condition, threads, close()."""

    _threads: list[threading.Thread]
    _up: Any  # the two directions, made by each relay
    _down: Any
    _listen_address: tuple[str, int]

    def __init__(self, profile: Profile, target: tuple[str, int]):
        self.profile = profile
        self.target = (target[0], int(target[1]))
        # reentrant, so that a wait_until predicate may read the relay's properties
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)   # notified on every counter change
        self._closed = False
        self._threads = []
        self._wake_r, self._wake_w = socket.socketpair()

    def _start(self, target: Callable[[], None], name: str) -> None:
        thread = threading.Thread(target=target, name=f"rosgate-emulator-{name}", daemon=True)
        self._threads.append(thread)
        thread.start()

    @property
    def address(self) -> tuple[str, int]:
        """Where clients send or connect to: ``(host, port)``."""
        return self._listen_address

    def _snapshot(self, direction: Any) -> Any:
        raise NotImplementedError

    @property
    def up(self) -> Any:
        """Counters of the direction client -> target (a snapshot: :class:`UdpCounters` or
        :class:`TcpCounters`)."""
        with self._lock:
            return self._snapshot(self._up)

    @property
    def down(self) -> Any:
        """Counters of the direction target -> client (a snapshot)."""
        with self._lock:
            return self._snapshot(self._down)

    def wait_until(self, predicate: Callable[[Any, Any], bool], timeout: float) -> bool:
        """Wait until ``predicate(up, down)`` (counter snapshots) is true, re-checked on every
        counter change (and connection change); return whether it became true within
        ``timeout`` seconds. The predicate may read the relay's properties too."""
        with self._changed:
            return self._changed.wait_for(
                lambda: predicate(self._snapshot(self._up), self._snapshot(self._down)),
                timeout)

    def _stop(self) -> None:
        """Subclasses: wake every thread (the lock is not held)."""

    def close(self) -> None:
        """Stop every thread and close every socket; what is in flight is discarded."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._changed.notify_all()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._stop()
        for thread in list(self._threads):
            if thread is not threading.current_thread():
                thread.join(JOIN_TIMEOUT)
        self._close_sockets()
        close_quietly(self._wake_r)
        close_quietly(self._wake_w)

    def _close_sockets(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
