"""Helpers for plugin tests: what they kept writing for themselves, once."""

from __future__ import annotations

import os
import random
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from rosgate import Address, Reason, StreamConnection
from rosgate.plugins import Plugins
from rosgate.spec import Delivery

TIMEOUT = 5.0  # seconds any single wait in the suites may take before the check fails


def free_port(host: str = "127.0.0.1") -> int:
    """A port free for both TCP and UDP on ``host`` (IPv4). With ``ROSGATE_TEST_PORTS=FIRST-LAST``
    set, the next such port of that range, in turn: test runs (and parallel workers of one run)
    given ranges of their own never hand out the same port, where ports the kernel picks from
    its shared ephemeral range may be picked again by another process before a test binds them.
    Every other port of the range, so that the one after a port is never handed out: an action
    takes its port and the next."""
    span = os.environ.get("ROSGATE_TEST_PORTS")
    if not span:
        return _kernel_port(host)
    first, last = (int(n) for n in span.split("-"))
    global _port_turn
    slots = (last - first + 1) // 2
    for _ in range(slots):
        port = first + 2 * ((os.getpid() + _port_turn) % slots)  # a subprocess starts elsewhere
        _port_turn += 1
        if _bindable(host, port):
            return port
    raise RuntimeError(f"no free port in ROSGATE_TEST_PORTS={span}")


_port_turn = 0


def _kernel_port(host: str) -> int:
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
            tcp.bind((host, 0))
            port = tcp.getsockname()[1]
            if _bindable(host, port, tcp=False):
                return port


def _bindable(host: str, port: int, tcp: bool = True) -> bool:
    kinds = (socket.SOCK_STREAM, socket.SOCK_DGRAM) if tcp else (socket.SOCK_DGRAM,)
    try:
        for kind in kinds:
            with socket.socket(socket.AF_INET, kind) as s:
                s.bind((host, port))
    except OSError:
        return False
    return True


def has_ipv6_loopback() -> bool:
    """Whether this kernel has ``::1`` (containers often lack it): skip IPv6 tests otherwise."""
    if not socket.has_ipv6:
        return False
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


def wait_until_blocked(native_id: int, timeout: float = 2.0) -> None:
    """Wait until the thread ``native_id`` sleeps in the kernel (a blocking receive), as Linux
    shows it in /proc; skip the test where that cannot be seen."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/self/task/{native_id}/wchan") as f:
                if f.read().strip() not in ("", "0"):
                    return
        except OSError:
            pytest.skip("cannot see where a thread sleeps (/proc/self/task/*/wchan)")
        time.sleep(0.005)
    pytest.fail(f"the thread did not block within {timeout} s")


def receive_exactly(connection: StreamConnection, size: int, timeout: float = TIMEOUT) -> bytes:
    """Read ``size`` bytes from a stream connection, failing the test on timeout or end."""
    data = bytearray()
    deadline = time.monotonic() + timeout
    while len(data) < size:
        left = deadline - time.monotonic()
        assert left > 0, f"only {len(data)} of {size} bytes within {timeout} s"
        chunk = connection.receive(size - len(data), left)
        assert chunk != b"", f"closed after {len(data)} of {size} bytes"
        if chunk:
            data += chunk
    return bytes(data)


def write_key(path: Path, key: bytes, mode: int = 0o600) -> Path:
    """Write a key file as ``rosgate keygen`` does (the key, a newline, mode 0600)."""
    path.write_bytes(key + b"\n")
    path.chmod(mode)
    return path


def mutations(valid: bytes, rng: random.Random, count: int) -> Iterator[bytes]:
    """``count`` damaged copies of ``valid``: bytes replaced, deleted and inserted, 1 to 3 times."""
    for _ in range(count):
        data = bytearray(valid)
        for _ in range(rng.randrange(1, 4)):
            if not data:
                break
            position = rng.randrange(len(data))
            operation = rng.randrange(3)
            if operation == 0:
                data[position] = rng.randrange(256)
            elif operation == 1:
                del data[position:position + rng.randrange(1, 8)]
            else:
                data[position:position] = rng.randbytes(rng.randrange(1, 8))
        yield bytes(data)


class Frames:
    """Collects what a link hands to ``on_frame``, and the drops it reports — on the receiving
    side through ``on_lost``, on the sending side to a :meth:`sender` — as ``(topic id,
    reason)``; wait for a number of frames."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []
        self.drops: list[tuple[int | None, str]] = []
        self._cond = threading.Condition()

    def on_frame(self, frame: bytes, link: Any, source: Address) -> None:
        with self._cond:
            self.frames.append(bytes(frame))
            self._cond.notify_all()

    def on_lost(self, topic_id: int | None, reason: Reason) -> None:
        with self._cond:
            self.drops.append((topic_id, reason))

    def sender(self, topic_id: int, reliable: bool = False) -> Sender:
        """What a route is to a link's ``send``: its drops are recorded here."""
        return Sender(topic_id, reliable, self)


    def wait_count(self, count: int, timeout: float = TIMEOUT) -> list[bytes]:
        with self._cond:
            self._cond.wait_for(lambda: len(self.frames) >= count, timeout)
            return list(self.frames)


@dataclass
class Sender:
    """A :class:`rosgate.links.base.Sender` for tests: its drops go to a :class:`Frames`."""

    topic_id: int
    reliable: bool
    frames: Frames

    @property
    def delivery(self) -> Delivery:
        return Delivery(reliable=self.reliable)

    def drop(self, reason: Reason, detail: str = "") -> None:
        self.frames.on_lost(self.topic_id, reason)

    def on_wire(self, size: int, again: bool) -> None:
        pass

# -- used by the suites ------------------------------------------------------------------------

def frame_of(size: int, seed: int) -> bytes:
    """Test frames start as rosgate frames do ("RG"), so no whole frame looks like a fragment."""
    return (b"RG" + random.Random(seed).randbytes(size))[:size]


def in_thread(call: Callable[[], Any]) -> tuple[threading.Thread, threading.Event, list[Any]]:
    """Run ``call`` in a thread; wait until it blocks; return the thread, its end, its result."""
    result: list[Any] = []
    native: list[int] = []
    started, finished = threading.Event(), threading.Event()

    def run() -> None:
        native.append(threading.get_native_id())
        started.set()
        try:
            result.append(call())
        except Exception as exc:  # the suite asserts on what came back, exceptions included
            result.append(exc)
        finished.set()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert started.wait(TIMEOUT)
    wait_until_blocked(native[0])
    return thread, finished, result


def assert_registered(kind: str, cls: Any) -> None:
    registration = Plugins.discover().get(kind, cls.name)
    assert registration is not None, (
        f"no {kind} {cls.name!r} among the installed plugins: is the distribution installed, "
        f"with an entry point in the group 'rosgate'?")
    assert registration.cls is cls


class Closing:
    """Things to close when the test ends, last opened first."""

    def __init__(self) -> None:
        self.things: list[Any] = []

    def __call__(self, thing: Any) -> Any:
        self.things.append(thing)
        return thing

    def close_all(self) -> None:
        for thing in reversed(self.things):
            try:
                thing.close()
            except OSError:
                pass
