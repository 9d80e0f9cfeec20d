"""Faults on demand: a user-space proxy that breaks a link the way a test asks, where the relays
of :mod:`.udp` and :mod:`.tcp` shape it statistically.

:class:`TcpFaults` forwards TCP connections and can cut them (close both sides), stall them
(stop forwarding, sockets left open), slow them, refuse new ones, or mangle the next chunk
going upstream (corrupt or truncate bytes in the stream). :class:`UdpFaults`
forwards datagrams both ways and drops, duplicates, reorders, delays, corrupts and truncates
them at configurable rates, from a seeded RNG so a failing run can be replayed; unlike
:class:`~rosgate_emulator.UdpRelay` it gives each sender an upstream socket of its own (as a NAT
does), so several clients can share it. Both use real sockets on 127.0.0.1 and threads, count
what they did, and shut down cleanly.
"""

from __future__ import annotations

import heapq
import itertools
import random
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from .relay import SOCKET_BUFFER, close_quietly, shutdown_quietly

HOST = "127.0.0.1"
POLL = 0.1


class TcpFaults:
    """Listens on ``HOST:port`` and forwards each connection to ``HOST:target``."""

    def __init__(self, port: int, target: int):
        self.target = target
        self.stalled = threading.Event()    # set: nothing is forwarded (connections stay open)
        self.refusing = threading.Event()   # set: new connections are closed at once
        self.delay = 0.0                    # seconds added before forwarding each chunk
        self.mangle: Callable[[bytes], bytes] | None = None  # once, on the next upstream chunk
        self.accepted = 0
        self.captured: list[tuple[bool, bytes]] = []  # (upstream, chunk): what an eavesdropper saw
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((HOST, port))
        self._listener.listen(16)
        self._listener.settimeout(POLL)
        self._threads = [threading.Thread(target=self._accept_loop, daemon=True)]
        self._threads[0].start()

    @property
    def connections(self) -> int:
        with self._lock:
            return len(self._pairs)

    def cut(self) -> int:
        """Close every forwarded connection, both sides; return how many were cut."""
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for pair in pairs:
            for sock in pair:
                _close(sock)
        return len(pairs)

    def _accept_loop(self) -> None:
        while not self._closed.is_set():
            try:
                near, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if self.refusing.is_set():
                _close(near)
                continue
            try:
                far = socket.create_connection((HOST, self.target), timeout=2)
            except OSError:
                _close(near)
                continue
            with self._lock:
                self._pairs.append((near, far))
                self.accepted += 1
            for source, sink, upstream in ((near, far, True), (far, near, False)):
                thread = threading.Thread(target=self._pump, args=(source, sink, upstream),
                                          daemon=True)
                thread.start()
                self._threads.append(thread)

    def _pump(self, source: socket.socket, sink: socket.socket, upstream: bool) -> None:
        source.settimeout(POLL)
        while not self._closed.is_set():
            if self.stalled.is_set():
                time.sleep(POLL / 4)  # not reading: the sender's buffers fill, as on a dead link
                continue
            try:
                data = source.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                break
            if not data:
                break
            if self.delay:
                time.sleep(self.delay)
            self.captured.append((upstream, data))
            if upstream and self.mangle is not None:
                mangle, self.mangle = self.mangle, None
                data = mangle(data)
            try:
                sink.sendall(data)
            except OSError:
                break
        _close(source)
        _close(sink)

    def close(self) -> None:
        self._closed.set()
        _close(self._listener)
        self.cut()
        for thread in self._threads:
            thread.join(2)


@dataclass
class UdpRates:
    """Probability of each fault per datagram (independent draws)."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0    # held back and sent after the next datagram
    delay: float = 0.0      # sent after ``delay_s``
    corrupt: float = 0.0    # one byte flipped
    truncate: float = 0.0   # cut at a random length
    delay_s: float = 0.05


class UdpFaults:
    """Receives datagrams on ``HOST:port`` and forwards them to ``HOST:target``; answers from the
    target go back to the sender, through the same faults. One upstream socket per sender, so the
    target sees each sender at an address of its own (as through a NAT)."""

    def __init__(self, port: int, target: int, rates: UdpRates | None = None, seed: int = 1):
        self.target = (HOST, target)
        self.rates = rates or UdpRates()
        self.rng = random.Random(seed)
        self.counts: Counter = Counter()
        self.captured: list[tuple[bool, bytes]] = []  # (upstream, datagram) as they came in
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._front = _udp_socket((HOST, port))
        self._upstream: dict[tuple[str, int], socket.socket] = {}  # sender -> its socket
        self._held: dict[socket.socket, tuple[bytes, tuple[str, int]]] = {}  # for reordering
        self._later: list[tuple[float, int, socket.socket, bytes, tuple[str, int]]] = []
        self._order = itertools.count()
        self._threads = [threading.Thread(target=self._front_loop, daemon=True),
                         threading.Thread(target=self._delayed_loop, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _front_loop(self) -> None:
        while not self._closed.is_set():
            try:
                data, sender = self._front.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            self.captured.append((True, data))
            with self._lock:
                upstream = self._upstream.get(sender)
                if upstream is None:
                    upstream = self._upstream[sender] = _udp_socket((HOST, 0))
                    thread = threading.Thread(target=self._back_loop, args=(upstream, sender),
                                              daemon=True)
                    thread.start()
                    self._threads.append(thread)
            self._forward(upstream, data, self.target)

    def rebind(self) -> None:
        """Forward each sender's datagrams from a new socket (a new port), as a NAT that lost
        its mapping does: the target sees its clients at new addresses."""
        with self._lock:
            for sender, old in list(self._upstream.items()):
                upstream = self._upstream[sender] = _udp_socket((HOST, 0))
                thread = threading.Thread(target=self._back_loop, args=(upstream, sender),
                                          daemon=True)
                thread.start()
                self._threads.append(thread)
                old.close()  # its thread ends; answers to the old port are lost, as behind a NAT

    def _back_loop(self, upstream: socket.socket, sender: tuple[str, int]) -> None:
        while not self._closed.is_set():
            try:
                data, _ = upstream.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            self.captured.append((False, data))
            self._forward(self._front, data, sender)

    def _forward(self, sock: socket.socket, data: bytes, to: tuple[str, int]) -> None:
        r, rng = self.rates, self.rng
        with self._lock:
            self.counts["in"] += 1
            if rng.random() < r.drop:
                self.counts["dropped"] += 1
                return
            damaged = data
            if data and rng.random() < r.corrupt:
                i = rng.randrange(len(data))
                damaged = data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:]
                self.counts["corrupted"] += 1
            if len(data) > 1 and rng.random() < r.truncate:
                damaged = damaged[:rng.randrange(1, len(data))]
                self.counts["truncated"] += 1
            if damaged is not data:
                self.counts["faulted"] += 1  # datagrams damaged either way, once each
                data = damaged
            copies = 2 if rng.random() < r.duplicate else 1
            self.counts["duplicated"] += copies - 1
            if rng.random() < r.delay:
                self.counts["delayed"] += 1
                heapq.heappush(self._later, (time.monotonic() + r.delay_s, next(self._order),
                                             sock, data, to))
                return
            held = self._held.pop(sock, None)
            if held is None and rng.random() < r.reorder:
                self.counts["reordered"] += 1
                self._held[sock] = (data, to)
                return
        for _ in range(copies):
            _send(sock, data, to)
        if held is not None:
            _send(sock, *held)

    def _delayed_loop(self) -> None:
        while not self._closed.wait(0.005):
            now = time.monotonic()
            due = []
            with self._lock:
                while self._later and self._later[0][0] <= now:
                    due.append(heapq.heappop(self._later))
            for _, _, sock, data, to in due:
                _send(sock, data, to)

    def close(self) -> None:
        self._closed.set()
        with self._lock:
            sockets = [self._front, *self._upstream.values()]
        for thread in self._threads:
            thread.join(2)
        for sock in sockets:
            sock.close()


class FaultProxy:
    """TCP and UDP on one port number, as a client's ``server:`` address is: the main line and
    the datagram topics both go through the faults."""

    def __init__(self, port: int, target: int, rates: UdpRates | None = None, seed: int = 1):
        self.port = port
        self.tcp = TcpFaults(port, target)
        self.udp = UdpFaults(port, target, rates, seed)

    def close(self) -> None:
        self.tcp.close()
        self.udp.close()


def _udp_socket(address: tuple[str, int]) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
    sock.bind(address)
    sock.settimeout(POLL)
    return sock


def _send(sock: socket.socket, data: bytes, to: tuple[str, int]) -> None:
    try:
        sock.sendto(data, to)
    except OSError:
        pass  # the proxy is a lossy link: a failed send is one more loss


def _close(sock: socket.socket) -> None:
    shutdown_quietly(sock)
    close_quietly(sock)
