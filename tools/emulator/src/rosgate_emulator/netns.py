"""Real kernel links: two network namespaces joined by a veth pair, optionally capped by the
kernel's ``tbf`` qdisc (:class:`NetnsPair`, root only)."""

from __future__ import annotations

import ctypes
import ctypes.util
import itertools
import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

_CLONE_NEWNET = 0x40000000
_NETNS_DIR = "/var/run/netns"
_netns_serial = itertools.count()
_netns_unavailable: str | None | bool = False   # False: not checked yet


def _setns(fd: int) -> None:
    libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    if libc.setns(fd, _CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"setns: {os.strerror(err)}")


class NetnsPair:
    """Two network namespaces, ``a`` and ``b``, joined by a veth pair (``va`` in a, ``vb`` in b)
    with addresses ``10.99.x.1/24`` and ``10.99.x.2/24`` (``x`` differs per instance in a
    process). ``rate`` (bit/s) caps both directions with the kernel's ``tbf`` qdisc (``burst``
    bytes, default 10 ms at the rate and at least 3,000; ``latency``: the most a packet may wait
    in tbf's queue before it is dropped). Root only: :meth:`unavailable` says why not.

    A context manager: entering creates everything (deleting what it made if a step fails),
    leaving stops the processes :meth:`popen` started and deletes both namespaces (the veth
    pair goes with them), even after errors. Sockets :meth:`socket` made keep their namespace
    alive until they are closed.
    """

    def __init__(self, rate: float | None = None, *, burst: int | None = None,
                 latency: float = 0.05):
        serial = next(_netns_serial)
        self.subnet = (os.getpid() + serial) % 254 + 1
        tag = f"{os.getpid()}-{serial}"
        self.namespaces = {"a": f"rosgate-{tag}-a", "b": f"rosgate-{tag}-b"}
        self.devices = {"a": "va", "b": "vb"}
        self.addresses = {"a": f"10.99.{self.subnet}.1", "b": f"10.99.{self.subnet}.2"}
        self.rate = rate
        self.burst = burst if burst is not None else (
            None if rate is None else max(3000, int(rate / 8 / 100)))
        self.latency = latency
        self._created: list[str] = []
        self._processes: list[subprocess.Popen] = []

    @staticmethod
    def unavailable() -> str | None:
        """Why namespaces cannot be made here (``None``: they can). Checked once per process."""
        global _netns_unavailable
        if _netns_unavailable is False:
            _netns_unavailable = NetnsPair._check()
        assert not isinstance(_netns_unavailable, bool)  # checked: a reason or None
        return _netns_unavailable

    @staticmethod
    def _check() -> str | None:
        if not sys.platform.startswith("linux"):
            return "network namespaces are Linux only"
        if os.geteuid() != 0:
            return "network namespaces need root (CI runs these tests as root)"
        for tool in ("ip", "tc"):
            if shutil.which(tool) is None:
                return f"the {tool!r} command (iproute2) is missing"
        probe = f"rosgate-probe-{os.getpid()}"
        made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
        if made.returncode != 0:
            return f"'ip netns add' fails here: {made.stderr.strip()}"
        subprocess.run(["ip", "netns", "del", probe], capture_output=True)
        return None

    def address(self, side: str) -> str:
        """The IPv4 address of ``side`` (``"a"`` or ``"b"``) on the veth pair."""
        return self.addresses[side]

    def __enter__(self) -> NetnsPair:
        try:
            for side in ("a", "b"):
                _command("ip", "netns", "add", self.namespaces[side])
                self._created.append(self.namespaces[side])
            _command("ip", "-n", self.namespaces["a"], "link", "add", "va", "type", "veth",
                     "peer", "name", "vb", "netns", self.namespaces["b"])
            for side in ("a", "b"):
                ns, dev = self.namespaces[side], self.devices[side]
                _command("ip", "-n", ns, "addr", "add", f"{self.addresses[side]}/24", "dev", dev)
                _command("ip", "-n", ns, "link", "set", "lo", "up")
                _command("ip", "-n", ns, "link", "set", dev, "up")
                if self.rate is not None:
                    _command("tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "tbf",
                             "rate", f"{int(self.rate)}bit", "burst", str(self.burst),
                             "latency", f"{max(1, round(self.latency * 1000))}ms")
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the processes started here, then delete both namespaces (idempotent)."""
        for process in self._processes:
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(2)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
        self._processes.clear()
        errors = []
        while self._created:
            ns = self._created.pop()
            result = subprocess.run(["ip", "netns", "del", ns], capture_output=True, text=True)
            if result.returncode != 0:
                errors.append(f"{ns}: {result.stderr.strip()}")
        if errors:
            raise RuntimeError("could not delete network namespaces: " + "; ".join(errors))

    def command(self, side: str, argv: Sequence[str]) -> list[str]:
        """``argv`` prefixed to run inside the namespace of ``side``."""
        return ["ip", "netns", "exec", self.namespaces[side], *argv]

    def run(self, side: str, argv: Sequence[str], **kwargs: Any) -> subprocess.CompletedProcess:
        """``subprocess.run`` of ``argv`` inside ``side``'s namespace (same keyword arguments)."""
        return subprocess.run(self.command(side, argv), **kwargs)

    def popen(self, side: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen:
        """``subprocess.Popen`` inside ``side``'s namespace; stopped when the pair closes."""
        process = subprocess.Popen(self.command(side, argv), **kwargs)
        self._processes.append(process)
        return process

    @contextmanager
    def inside(self, side: str) -> Iterator[None]:
        """Move the calling thread into ``side``'s namespace for the ``with`` block: sockets
        made there belong to it (and stay there once the thread is back)."""
        target = os.open(os.path.join(_NETNS_DIR, self.namespaces[side]), os.O_RDONLY)
        home = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
        try:
            _setns(target)
            try:
                yield
            finally:
                _setns(home)
        finally:
            os.close(target)
            os.close(home)

    def socket(self, side: str, family: int = socket.AF_INET,
               type: int = socket.SOCK_DGRAM) -> socket.socket:
        """A new socket in ``side``'s namespace (usable from any thread)."""
        with self.inside(side):
            return socket.socket(family, type)


def _command(*argv: str) -> None:
    result = subprocess.run(argv, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {result.stderr.strip() or result.returncode}")
