"""A user-space emulator of a bad link: rate, delay, jitter, loss, MTU and a bounded queue.

This machine (and many CI machines) has no ``netem``, yet robots live on Wi-Fi and radios.
The relays here sit between two endpoints on real sockets and make the path between them
behave like a constrained link, so a test (or the benchmark's "constrained link" section) can
see what a bridge does when bytes are slow, late and sometimes lost. Standard library only:
nothing here imports rosgate.

What is emulated
----------------

Each direction of a relay is an independent link, described by a :class:`Profile`:

* **Rate** — a token bucket of ``rate`` bit/s holding at most ``burst`` bytes. A packet
  leaves the link (its last bit is sent) at ``max(now, link free) + missing tokens / rate``;
  with ``burst=0`` (the default) that is plain serialisation, ``size * 8 / rate`` after the
  link became free. Sizes count the IP headers (and UDP/TCP headers) of every packet.
* **Queue** — bytes accepted but not yet sent onto the link (``queue``, counted in wire bytes).
  UDP: a datagram that does not fit is tail-dropped (``queue_full``). TCP: the relay stops
  reading from the source socket until the queue has room (backpressure); bytes are never
  dropped.
* **Delay and jitter** — a packet arrives ``delay + U(0, jitter)`` after it left the link:
  jitter is *uniform* on ``[0, jitter]`` and only ever adds, so ``delay`` is the minimum one-way
  latency and the mean is ``delay + jitter / 2``. Order is kept (a packet never overtakes the
  one before it, it waits behind it) unless ``reorder=True`` (UDP only; TCP always keeps order).
* **MTU and IPv4 fragments** — a UDP datagram of ``n`` bytes travels as
  :func:`ip_fragments` ``(n, mtu)`` IPv4 packets: one if ``n + 28 <= mtu``, else
  ``ceil((n + 8) / (8 * floor((mtu - 20) / 8)))`` fragments (each fragment has its own 20-byte IP
  header, the 8-byte UDP header rides in the first, fragment payloads are multiples of 8).
  E.g. at MTU 1500: 1,472 bytes is 1 packet, 1,473 is 2, 4,000 is 3 (1480 + 1480 + 1048).
  Wire bytes: :func:`udp_wire_bytes` ``= n + 8 + 20 * fragments``.
* **Loss** — each IP packet is lost with probability ``loss``, independently. A UDP datagram
  is lost when any one of its fragments is (so a 3-fragment datagram at 10 % is lost with
  probability 1 - 0.9**3 = 27.1 %). A lost datagram still took its time on the link.
  TCP (segments of ``mss = mtu - 40`` bytes, 40 wire bytes of headers each) never loses bytes:
  a lost segment is retransmitted after the retransmission timeout (:attr:`Profile.rto_s`,
  by default ``max(200 ms, 2 * RTT)`` with ``RTT = 2 * (delay + jitter)``: 200 ms is Linux's
  minimum RTO), doubling for each further loss of the same segment, and everything behind it
  waits (head-of-line blocking). Each retransmitted copy takes link time too.
* **Seeds** — ``seed`` makes every run the same: each direction has its own random streams,
  one for loss and one for jitter, derived from the seed and the direction's name. The UDP
  loss draw is made for every datagram in arrival order (before the queue check), so the same
  seed and the same datagrams give the same loss pattern whatever the timing.

What is not emulated
--------------------

No duplication, no corruption, no truncation (``tests/faults.py`` does those for the
end-to-end tests); no bursty (Gilbert-Elliott) loss, no varying rate, no link-layer
retransmission. TCP is modelled optimistically: the relay's sender never slows down after
a loss (no congestion window, no slow start, no fast retransmit or SACK), so it shows
head-of-line blocking and the cost of retransmissions but not the throughput collapse of real
TCP under heavy loss; treat its throughput as an upper bound. The relay's own sockets are
real: TCP connection set-up and the relay's kernel buffers (4 MiB) add nothing modelled. The
fragment arithmetic is IPv4's even when the relay listens on IPv6. :class:`UdpRelay` answers
one client at a time (the last one that sent), as a NAT with one mapping would.

Use from a test
---------------

::

    from rosgate_emulator import WIFI, Profile, UdpRelay, TcpRelay

    def test_my_link_on_wifi(bridge_b_port):
        lossy = Profile(rate=2e6, delay=0.01, jitter=0.002, loss=0.1, seed=7)
        with UdpRelay(lossy, target=("127.0.0.1", bridge_b_port)) as link:
            ...                                   # point side A at link.address
            assert link.wait_until(lambda up, down: up.datagrams_delivered >= 100, timeout=5)
            assert link.up.dropped["loss"] > 0

The relay answers the address it last heard from, so a bridge that replies to the source it
saw works through it. ``close()`` (or leaving the ``with``) stops its threads and closes its
sockets at once; datagrams still in flight are discarded. :meth:`UdpRelay.wait_until` and
:meth:`TcpRelay.wait_until` wait on the counters without polling. A delivery is counted just
before it is handed to the socket, so a receiver never holds more than the counters say.

Timing is faithful while the machine keeps up: a UDP datagram's time on the emulated link
starts when the kernel stamped its arrival at the relay (so a relay thread that runs late does
not add delay), and ``late_max`` in the counters says how much later than due the relay
handed anything over. If that is not small beside ``jitter``, a busy machine, not the
profile, shaped the latencies.

Use from the benchmark
----------------------

Put a relay between the two bridges, one per port the far bridge listens on (a
:class:`TcpRelay` for the main line, a :class:`UdpRelay` per UDP port), with the :data:`WIFI`
preset (20 Mbit/s, 10 ms, 2 ms jitter, 1 % loss, MTU 1500)::

    with UdpRelay(WIFI, target=("127.0.0.1", port_b)) as link:
        ...   # bridge A's peer / server address = link.address

To keep the relay's threads away from the measured processes' GIL, run it as a process of
its own; it prints its address, runs until SIGINT/SIGTERM, then prints its counters as JSON::

    python -m rosgate_emulator udp --target 127.0.0.1:13001 --listen 127.0.0.1:12001 \\
        --preset wifi [--rate 1e7] [--loss 0.05] [--seed 3]

Real kernel links: :class:`NetnsPair` (root only) makes two network namespaces joined by a
veth pair, optionally capped by the kernel's ``tbf`` qdisc, for tests that need two hosts
with their own IP stacks; put a relay inside for delay, jitter and loss (``netem`` is not
available here).
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import dataclasses
import heapq
import itertools
import json
import os
import random
import selectors
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

__all__ = [
    "IP_HEADER", "MAX_UDP_PAYLOAD", "NetnsPair", "PRESETS", "Profile", "TCP_HEADER", "TcpCounters",
    "TcpRelay", "UDP_HEADER", "UdpCounters", "UdpRelay", "WIFI", "ip_fragments",
    "udp_wire_bytes",
]

IP_HEADER = 20          # IPv4 header without options
UDP_HEADER = 8
TCP_HEADER = 20         # without options
MAX_UDP_PAYLOAD = 65507  # 65535 - 20 - 8
RTO_MIN = 0.2           # Linux's TCP_RTO_MIN
SOCKET_BUFFER = 4 << 20  # the relays' kernel buffers, so the relay itself drops nothing
JOIN_TIMEOUT = 5.0


def ip_fragments(size: int, mtu: int = 1500) -> int:
    """How many IPv4 packets carry a UDP datagram of ``size`` payload bytes over ``mtu``.

    One if ``size + 8 + 20 <= mtu``; else the IP payload (``size + 8``) is cut into fragments
    of ``floor((mtu - 20) / 8) * 8`` bytes (the last one shorter), each with its own header.
    """
    if not 0 <= size <= MAX_UDP_PAYLOAD:
        raise ValueError(f"a UDP datagram over IPv4 holds 0 to {MAX_UDP_PAYLOAD} bytes, not {size}")
    ip_payload = size + UDP_HEADER
    if ip_payload + IP_HEADER <= mtu:
        return 1
    per_fragment = (mtu - IP_HEADER) // 8 * 8
    return -(-ip_payload // per_fragment)


def udp_wire_bytes(size: int, mtu: int = 1500) -> int:
    """Bytes a UDP datagram of ``size`` takes on the link: payload, UDP header, IP headers."""
    return size + UDP_HEADER + IP_HEADER * ip_fragments(size, mtu)


@dataclass(frozen=True)
class Profile:
    """How one direction of an emulated link behaves (both directions get the same profile,
    each with its own state and random streams). Change a copy with
    ``dataclasses.replace(WIFI, loss=0.05)``."""

    rate: float | None = None
    """Link rate in bit/s (a token bucket refilled at this rate); ``None``: unlimited (no
    serialisation time, the queue never fills)."""

    burst: int = 0
    """Size of the token bucket in bytes: that many bytes may leave back to back without
    serialisation time after the link was idle. 0: a plain serialising link."""

    delay: float = 0.0
    """One-way propagation delay in seconds, added to every packet after it left the link."""

    jitter: float = 0.0
    """Extra delay in seconds, drawn per packet uniformly on ``[0, jitter]`` (never negative:
    ``delay`` is the minimum latency, the mean is ``delay + jitter / 2``)."""

    reorder: bool = False
    """UDP only: let jitter reorder datagrams. False (default, as Wi-Fi mostly keeps order): a
    datagram whose draw would overtake the previous one arrives right after it instead.
    TCP always keeps order."""

    loss: float = 0.0
    """Probability that one MTU-sized IP packet is lost (UDP: a datagram is lost when any of
    its fragments is; TCP: the segment is retransmitted after :attr:`rto_s`)."""

    mtu: int = 1500
    """Largest IP packet in bytes. Larger UDP datagrams travel as IPv4 fragments
    (:func:`ip_fragments`); TCP segments carry ``mtu - 40`` bytes."""

    queue: int | None = 1 << 20
    """Bytes (on the wire, headers included) that may wait to be sent onto the link. UDP: a
    datagram that does not fit is dropped (``queue_full``); TCP: the relay stops reading from
    the sender. ``None``: unbounded."""

    rto: float | None = None
    """TCP retransmission timeout in seconds; ``None``: ``max(0.2, 2 * RTT)`` with
    ``RTT = 2 * (delay + jitter)`` (0.2 s is Linux's minimum RTO)."""

    seed: int | str | None = 0
    """Seed of the random streams (loss and jitter, per direction): the same seed and the same
    datagrams give the same UDP losses (TCP's also depend on how reads cut the stream).
    ``None``: fresh randomness from the OS on every relay."""

    def __post_init__(self) -> None:
        if self.rate is not None and not self.rate > 0:
            raise ValueError(f"rate must be > 0 bit/s or None, not {self.rate}")
        if self.burst < 0:
            raise ValueError(f"burst must be >= 0 bytes, not {self.burst}")
        if self.delay < 0 or self.jitter < 0:
            raise ValueError("delay and jitter must be >= 0 seconds")
        if not 0 <= self.loss < 1:
            raise ValueError(f"loss must be in [0, 1), not {self.loss}")
        if self.mtu < 68:
            raise ValueError(f"an IPv4 MTU is at least 68 bytes, not {self.mtu}")
        if self.queue is not None and self.queue <= 0:
            raise ValueError(f"queue must be > 0 bytes or None, not {self.queue}")
        if self.rto is not None and not self.rto > 0:
            raise ValueError(f"rto must be > 0 seconds or None, not {self.rto}")

    @property
    def rto_s(self) -> float:
        """The TCP retransmission timeout in effect (seconds)."""
        if self.rto is not None:
            return self.rto
        return max(RTO_MIN, 2 * 2 * (self.delay + self.jitter))

    @property
    def mss(self) -> int:
        """TCP payload bytes per segment: ``mtu`` minus 20 bytes of IP and 20 of TCP header."""
        return self.mtu - IP_HEADER - TCP_HEADER


WIFI = Profile(rate=20e6, delay=0.010, jitter=0.002, loss=0.01, mtu=1500, queue=250_000)
"""Issue 12's constrained link: 20 Mbit/s, 10 ms one way, 2 ms jitter, 1 % loss, MTU 1500,
a 250 kB queue (100 ms at the rate, about 170 full frames, like a Wi-Fi driver's)."""

PRESETS = {"wifi": WIFI}


@dataclass(frozen=True)
class UdpCounters:
    """One direction of a :class:`UdpRelay` (a snapshot)."""

    datagrams_in: int       # received from the source
    bytes_in: int           # their payload bytes
    datagrams_delivered: int  # handed to the socket toward the destination (counted just
    bytes_delivered: int      # before, so a receiver never has more than these say)
    dropped: dict[str, int]  # by reason: loss, queue_full (always present); no_client, unreachable
    queue_bytes: int        # wire bytes waiting to be sent onto the link now
    queue_max: int          # the most ever waiting
    late_max: float         # seconds: the most a datagram was handed over after it was due


@dataclass(frozen=True)
class TcpCounters:
    """One direction of a :class:`TcpRelay`, all its connections together (a snapshot)."""

    segments_in: int        # segments cut from what was read from the source
    bytes_in: int
    bytes_delivered: int    # handed to the destination socket (counted just before)
    retransmitted: int      # retransmissions (a segment lost twice counts twice)
    queue_bytes: int
    queue_max: int
    late_max: float         # seconds: the most bytes were handed over after they were due


def _rng(seed: int | str | None, direction: str, purpose: str) -> random.Random:
    if seed is None:
        return random.Random()
    return random.Random(f"rosgate.emulator:{seed}:{direction}:{purpose}")


class _Link:
    """The model of one direction: token bucket, queue accounting, loss and jitter draws.

    Not thread-safe: callers hold their relay's lock. Times are ``time.monotonic()``.
    """

    def __init__(self, profile: Profile, direction: str):
        self.profile = profile
        self._loss = _rng(profile.seed, direction, "loss")
        self._jitter = _rng(profile.seed, direction, "jitter")
        self._tokens = float(profile.burst)
        self._tokens_at = time.monotonic()
        self._free = 0.0                                   # when the last packet left
        self._backlog: deque[tuple[float, int]] = deque()  # (departure, wire bytes), FIFO
        self.queue_bytes = 0
        self.queue_max = 0

    def drain(self, now: float) -> None:
        backlog = self._backlog
        while backlog and backlog[0][0] <= now:
            self.queue_bytes -= backlog.popleft()[1]

    def room(self, now: float) -> int | None:
        """Wire bytes the queue can still take (``None``: unbounded)."""
        self.drain(now)
        return None if self.profile.queue is None else self.profile.queue - self.queue_bytes

    def next_departure(self) -> float | None:
        return self._backlog[0][0] if self._backlog else None

    def lost(self, packets: int) -> bool:
        """Draw the fate of ``packets`` IP packets: True when any one is lost."""
        p = self.profile.loss
        if p <= 0:
            return False
        return sum(self._loss.random() < p for _ in range(packets)) > 0

    def losses(self) -> int:
        """TCP: how many times in a row one segment is lost (0: it arrives the first time)."""
        p, k = self.profile.loss, 0
        while p > 0 and k < 16 and self._loss.random() < p:
            k += 1
        return k

    def send(self, now: float, wire: int) -> float:
        """Put ``wire`` bytes on the link (the caller checked the queue); return when the last
        bit leaves."""
        rate = self.profile.rate
        if rate is None:
            return now
        bytes_per_s = rate / 8
        start = max(now, self._free)
        tokens = min(self.profile.burst,
                     self._tokens + (start - self._tokens_at) * bytes_per_s)
        if tokens >= wire:
            departure, tokens = start, tokens - wire
        else:
            departure, tokens = start + (wire - tokens) / bytes_per_s, 0.0
        self._tokens, self._tokens_at, self._free = tokens, departure, departure
        if departure > now:
            self._backlog.append((departure, wire))
            self.queue_bytes += wire
            self.queue_max = max(self.queue_max, self.queue_bytes)
        return departure

    def arrival(self, departure: float) -> float:
        """When a packet that left at ``departure`` arrives (order not yet enforced)."""
        jitter = self.profile.jitter
        extra = self._jitter.uniform(0.0, jitter) if jitter > 0 else 0.0
        return departure + self.profile.delay + extra


def _family(host: str) -> socket.AddressFamily:
    return socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)[0][0]


def _close(sock: socket.socket | None) -> None:
    if sock is not None:
        try:
            sock.close()
        except OSError:
            pass


def _shutdown(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass


class _Relay:
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
        _close(self._wake_r)
        _close(self._wake_w)

    def _close_sockets(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _UdpDirection:
    def __init__(self, relay: UdpRelay, name: str, sock: socket.socket):
        self.relay = relay
        self.link = _Link(relay.profile, name)
        self.sock = sock
        self.wakeup = threading.Condition(relay._lock)
        self.heap: list[tuple[float, int, bytes, Any]] = []
        self.serial = itertools.count()
        self.last_arrival = 0.0
        self.datagrams_in = self.bytes_in = 0
        self.datagrams_delivered = self.bytes_delivered = 0
        self.dropped: Counter[str] = Counter(loss=0, queue_full=0)
        self.late_max = 0.0

    def submit(self, data: bytes, destination: Any, now: float) -> None:
        """A datagram came in (the relay's lock is held)."""
        link, profile = self.link, self.relay.profile
        size = len(data)
        self.datagrams_in += 1
        self.bytes_in += size
        if destination is None:
            self.dropped["no_client"] += 1
            return
        fragments = ip_fragments(min(size, MAX_UDP_PAYLOAD), profile.mtu)
        wire = size + UDP_HEADER + IP_HEADER * fragments
        lost = link.lost(fragments)          # drawn first: the pattern does not depend on timing
        room = link.room(now)
        if room is not None and wire > room:
            self.dropped["queue_full"] += 1
            return
        departure = link.send(now, wire)
        if lost:
            self.dropped["loss"] += 1
            return
        arrival = link.arrival(departure)
        if not profile.reorder:
            arrival = max(arrival, self.last_arrival)
            self.last_arrival = arrival
        heapq.heappush(self.heap, (arrival, next(self.serial), data, destination))
        if self.heap[0][2] is data:
            self.wakeup.notify()

    def run(self) -> None:
        """The scheduler: deliver each datagram when it is due."""
        heap, relay = self.heap, self.relay
        while True:
            with self.wakeup:
                while True:
                    if relay._closed:
                        return
                    now = time.monotonic()
                    if heap and heap[0][0] <= now:
                        break
                    self.wakeup.wait(heap[0][0] - now if heap else None)
                self.late_max = max(self.late_max, now - heap[0][0])
                due = []
                while heap and heap[0][0] <= now:
                    due.append(heapq.heappop(heap))
                # counted before it is handed over, so a receiver never sees more than the
                # counters say; a datagram the socket refuses is moved to "unreachable"
                self.datagrams_delivered += len(due)
                self.bytes_delivered += sum(len(item[2]) for item in due)
                relay._changed.notify_all()
            refused = refused_bytes = 0
            for _, _, data, destination in due:
                try:
                    if destination is _TARGET:
                        self.sock.send(data)
                    else:
                        self.sock.sendto(data, destination)
                except OSError:
                    if relay._closed:
                        return
                    refused += 1                 # ICMP port unreachable from the target
                    refused_bytes += len(data)
            if refused:
                with self.wakeup:
                    self.datagrams_delivered -= refused
                    self.bytes_delivered -= refused_bytes
                    self.dropped["unreachable"] += refused
                    relay._changed.notify_all()


_TARGET = object()  # the destination of datagrams going up: the relay's connected socket


# Linux stamps each datagram as it reaches a socket (SO_TIMESTAMPNS, CLOCK_REALTIME): the
# emulated link starts from that instant, so a relay thread that runs late (a busy machine)
# does not add to the emulated delay; lateness then shows in the counters' late_max.
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS",
                          35 if sys.platform.startswith("linux") else None)
_TIMESPEC = struct.Struct("@qq")
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size) if _SO_TIMESTAMPNS else 0


def _arrival(ancillary: list[tuple[int, int, bytes]]) -> float:
    """When a datagram reached the relay's socket, on the ``time.monotonic()`` clock."""
    now = time.monotonic()
    for level, kind, value in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
            seconds, nanoseconds = _TIMESPEC.unpack(value[:_TIMESPEC.size])
            return min(now, seconds + nanoseconds * 1e-9 - (time.time() - now))
    return now


class UdpRelay(_Relay):
    """A UDP relay through an emulated link, both ways.

    Datagrams arriving at :attr:`address` go to ``target`` from a socket of the relay's own,
    bound to ``source`` (default: a free port; :attr:`source_address`); what ``target`` sends
    to that socket goes back to the last client address that sent (dropped as ``no_client``
    before any did). A bridge that answers the source it saw thus works through the relay; one
    configured with a fixed peer address (role ``peer``) gets ``source_address`` as its peer.
    Each direction is an independent link with ``profile`` (its own bucket, queue and random
    streams); counters in :attr:`up` (client -> target) and :attr:`down` (target -> client).
    """

    def __init__(self, profile: Profile, target: tuple[str, int],
                 listen: tuple[str, int] = ("127.0.0.1", 0),
                 source: tuple[str, int] | None = None):
        super().__init__(profile, target)
        self._client: Any = None
        self._outer: socket.socket | None = None
        self._inner: socket.socket | None = None
        try:
            self._outer = socket.socket(_family(listen[0]), socket.SOCK_DGRAM)
            self._inner = socket.socket(_family(self.target[0]), socket.SOCK_DGRAM)
            for sock in (self._outer, self._inner):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)
                if _SO_TIMESTAMPNS:
                    sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            self._outer.bind(listen)
            if source is not None:
                self._inner.bind(source)
            self._inner.connect(self.target)
        except BaseException:
            self._close_sockets()
            _close(self._wake_r)
            _close(self._wake_w)
            raise
        self._listen_address = self._outer.getsockname()[:2]
        self._source_address = self._inner.getsockname()[:2]
        self._up = _UdpDirection(self, "up", self._inner)
        self._down = _UdpDirection(self, "down", self._outer)
        self._start(self._read, "udp-read")
        self._start(self._up.run, "udp-up")
        self._start(self._down.run, "udp-down")

    @property
    def source_address(self) -> tuple[str, int]:
        """Where the relay sends to ``target`` from, and where the target's answers go."""
        return self._source_address

    def _read(self) -> None:
        """One thread reads both sockets (and the wake-up pipe that close() writes to)."""
        assert self._outer is not None and self._inner is not None
        with selectors.DefaultSelector() as selector:
            selector.register(self._outer, selectors.EVENT_READ, "up")
            selector.register(self._inner, selectors.EVENT_READ, "down")
            selector.register(self._wake_r, selectors.EVENT_READ, None)
            while True:
                for key, _ in selector.select():
                    if key.data is None or self._closed:
                        return
                    for _ in range(256):     # drain, but let the other direction have its turn
                        try:
                            sock = key.fileobj
                            assert isinstance(sock, socket.socket)
                            data, ancillary, _, source = sock.recvmsg(
                                65535, _ANCILLARY, socket.MSG_DONTWAIT)
                        except (BlockingIOError, InterruptedError):
                            break
                        except OSError:      # ICMP port unreachable from the target, or closed
                            if self._closed:
                                return
                            continue
                        now = _arrival(ancillary)
                        with self._lock:
                            if key.data == "up":
                                self._client = source
                                self._up.submit(data, _TARGET, now)
                            else:
                                self._down.submit(data, self._client, now)
                            self._changed.notify_all()

    def _snapshot(self, d: _UdpDirection) -> UdpCounters:
        d.link.drain(time.monotonic())
        return UdpCounters(d.datagrams_in, d.bytes_in, d.datagrams_delivered, d.bytes_delivered,
                           dict(d.dropped), d.link.queue_bytes, d.link.queue_max, d.late_max)

    def _stop(self) -> None:
        with self._lock:
            self._up.wakeup.notify_all()
            self._down.wakeup.notify_all()

    def _close_sockets(self) -> None:
        _close(self._outer)
        _close(self._inner)


class _Pipe:
    """One direction of one TCP connection: a reader thread and a delivering thread."""

    def __init__(self, connection: _TcpConnection, direction: _TcpDirection,
                 source: socket.socket, destination: socket.socket):
        self.connection = connection
        self.direction = direction
        self.source, self.destination = source, destination
        lock = connection.relay._lock
        self.data_ready = threading.Condition(lock)   # the deliverer waits here
        self.room = threading.Condition(lock)         # the reader waits here
        self.items: deque[tuple[float, bytes | None]] = deque()  # (due, piece); None: EOF
        self.pending = 0          # bytes read and not yet delivered (queued, in flight, held)
        self.last = 0.0           # arrival of the last piece: nothing may overtake it

    def read(self) -> None:
        relay = self.connection.relay
        profile, link = relay.profile, self.direction.link
        mss, window = profile.mss, relay.window
        need = 0 if profile.queue is None else min(profile.queue, mss + IP_HEADER + TCP_HEADER)
        try:
            while True:
                with self.room:
                    while True:
                        if self.connection.stopped:
                            return
                        now = time.monotonic()
                        room = link.room(now)
                        if self.pending < window and (room is None or room >= need
                                                      or link.queue_bytes == 0):
                            break
                        timeout = None
                        if room is not None and room < need:
                            next_departure = link.next_departure()
                            if next_departure is not None:
                                timeout = max(0.0, next_departure - now)
                        self.room.wait(timeout)
                    size = 65536 if room is None else _payload_fitting(room, mss)
                    size = max(1, min(size, 65536, window - self.pending))
                try:
                    data = self.source.recv(size)
                except OSError:
                    self.connection.abort()
                    return
                with self.room:
                    if not data:
                        due = max(self.last, time.monotonic() + profile.delay)
                        self.items.append((due, None))
                        self.last = due
                        self.data_ready.notify()
                        return
                    self._schedule(data, time.monotonic())
        finally:
            self.connection.thread_done()

    def _schedule(self, data: bytes, now: float) -> None:
        """Cut ``data`` into segments and put them on the link (the lock is held)."""
        relay, direction = self.connection.relay, self.direction
        link, mss, rto = direction.link, relay.profile.mss, relay.profile.rto_s
        view = memoryview(data)
        segments = retransmitted = 0
        for offset in range(0, len(data), mss):
            piece = bytes(view[offset:offset + mss])
            wire = len(piece) + IP_HEADER + TCP_HEADER
            losses = link.losses()
            departure = link.send(now, wire)
            for _ in range(losses):              # every retransmitted copy takes link time
                link.send(now, wire)
            hold = rto * (2 ** losses - 1)       # rto, then 2 rto, 4 rto, ... (backoff)
            arrival = max(link.arrival(departure) + hold, self.last)
            self.last = arrival
            self.items.append((arrival, piece))
            segments += 1
            retransmitted += losses
        self.pending += len(data)
        direction.segments_in += segments
        direction.bytes_in += len(data)
        direction.retransmitted += retransmitted
        self.data_ready.notify()
        relay._changed.notify_all()

    def deliver(self) -> None:
        relay, items = self.connection.relay, self.items
        try:
            while True:
                with self.data_ready:
                    while True:
                        if self.connection.stopped:
                            return
                        now = time.monotonic()
                        if items and items[0][0] <= now:
                            break
                        self.data_ready.wait(items[0][0] - now if items else None)
                    direction = self.direction
                    direction.late_max = max(direction.late_max, now - items[0][0])
                    chunks, end = [], False
                    while items and items[0][0] <= now:
                        piece = items.popleft()[1]
                        if piece is None:
                            end = True
                            break
                        chunks.append(piece)
                    data = b"".join(chunks)
                    # counted before it is handed over, so a receiver never sees more
                    self.direction.bytes_delivered += len(data)
                    relay._changed.notify_all()
                if data:
                    try:
                        self.destination.sendall(data)
                    except OSError:
                        with self.room:
                            self.direction.bytes_delivered -= len(data)
                        self.connection.abort()
                        return
                    with self.room:
                        self.pending -= len(data)
                        self.room.notify()
                if end:
                    try:
                        self.destination.shutdown(socket.SHUT_WR)
                    except OSError:
                        pass
                    return
        finally:
            self.connection.thread_done()


def _payload_fitting(room: int, mss: int) -> int:
    """The most payload bytes whose segments (40 header bytes each) fit in ``room``."""
    segment = mss + IP_HEADER + TCP_HEADER
    full, rest = divmod(room, segment)
    return full * mss + max(0, rest - IP_HEADER - TCP_HEADER)


class _TcpDirection:
    def __init__(self, relay: TcpRelay, name: str):
        self.link = _Link(relay.profile, name)
        self.segments_in = self.bytes_in = self.bytes_delivered = self.retransmitted = 0
        self.late_max = 0.0


class _TcpConnection:
    def __init__(self, relay: TcpRelay, client: socket.socket, upstream: socket.socket):
        self.relay = relay
        self.sockets = (client, upstream)
        self.stopped = False
        self._running = 4
        self.pipes = (_Pipe(self, relay._up, client, upstream),
                      _Pipe(self, relay._down, upstream, client))

    def start(self) -> None:
        """Start the four threads (the relay's lock is held)."""
        for pipe, name in zip(self.pipes, ("up", "down"), strict=True):
            self.relay._start(pipe.read, f"tcp-read-{name}")
            self.relay._start(pipe.deliver, f"tcp-deliver-{name}")

    def abort(self) -> None:
        """Tear the connection down both ways (any thread, the lock not held)."""
        with self.relay._lock:
            if self.stopped:
                return
            self.stopped = True
            for pipe in self.pipes:
                pipe.room.notify_all()
                pipe.data_ready.notify_all()
        for sock in self.sockets:
            _shutdown(sock)

    def thread_done(self) -> None:
        with self.relay._lock:
            self._running -= 1
            last = self._running == 0
            if last:
                self.relay._connections.discard(self)
                self.relay._changed.notify_all()
        if last:
            for sock in self.sockets:
                _close(sock)


class TcpRelay(_Relay):
    """A TCP relay through an emulated link: each accepted connection is joined to a new
    connection to ``target`` and bytes are piped both ways through two links with ``profile``
    (one per direction, shared by all connections). Order is always kept and bytes are never
    lost: a lost segment holds itself and everything behind it for the retransmission timeout.
    When the queue is full the relay stops reading from the sender (TCP backpressure), and it
    also stops when ``window`` bytes of one connection's direction are not yet delivered (the
    receiver's window). An end of stream (FIN) is passed on after the data before it; a reset
    or error on either side closes both.

    Segments are cut from each read of the relay (at most ``mss`` bytes each, no Nagle), so
    the TCP loss pattern depends on how reads cut the stream, not only on the seed. The queue
    is checked before each read; the retransmitted copies of that read's lost segments, and
    other connections reading at the same moment, may take it a few segments past ``queue``.
    """

    def __init__(self, profile: Profile, target: tuple[str, int],
                 listen: tuple[str, int] = ("127.0.0.1", 0), *, window: int = 4 << 20):
        super().__init__(profile, target)
        self.window = window
        self._connections: set[_TcpConnection] = set()
        self.accepted = 0           # connections accepted
        self.connect_failed = 0     # accepted connections closed because target refused
        self._up = _TcpDirection(self, "up")
        self._down = _TcpDirection(self, "down")
        self._listener = socket.socket(_family(listen[0]), socket.SOCK_STREAM)
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(listen)
            self._listener.listen(64)
        except BaseException:
            self._close_sockets()
            _close(self._wake_r)
            _close(self._wake_w)
            raise
        self._listen_address = self._listener.getsockname()[:2]
        self._start(self._accept, "tcp-accept")

    @property
    def connections(self) -> int:
        """Connections open now."""
        with self._lock:
            return len(self._connections)

    def _accept(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._listener, selectors.EVENT_READ, "accept")
            selector.register(self._wake_r, selectors.EVENT_READ, None)
            while True:
                for key, _ in selector.select():
                    if key.data is None or self._closed:
                        return
                    try:
                        client, _ = self._listener.accept()
                    except OSError:
                        continue
                    try:
                        upstream = socket.create_connection(self.target, timeout=JOIN_TIMEOUT)
                    except OSError:
                        _close(client)
                        with self._lock:
                            self.accepted += 1
                            self.connect_failed += 1
                            self._changed.notify_all()
                        continue
                    for sock in (client, upstream):
                        sock.settimeout(None)
                        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    with self._lock:
                        self.accepted += 1
                        if self._closed:
                            _close(client)
                            _close(upstream)
                            return
                        self._threads = [t for t in self._threads if t.is_alive()]
                        connection = _TcpConnection(self, client, upstream)
                        self._connections.add(connection)
                        connection.start()
                        self._changed.notify_all()

    def _snapshot(self, d: _TcpDirection) -> TcpCounters:
        d.link.drain(time.monotonic())
        return TcpCounters(d.segments_in, d.bytes_in, d.bytes_delivered, d.retransmitted,
                           d.link.queue_bytes, d.link.queue_max, d.late_max)

    def _stop(self) -> None:
        with self._lock:
            connections = list(self._connections)
        for connection in connections:
            connection.abort()

    def _close_sockets(self) -> None:
        _close(self._listener)


# --- real kernel links: two network namespaces joined by a veth pair (root only) -----------

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


# --- a relay as a process of its own: python -m rosgate_emulator ---------------------------

def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host.strip("[]") or "127.0.0.1", int(port)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rosgate_emulator",
        description="Relay UDP datagrams or TCP connections through an emulated link until "
                    "SIGINT/SIGTERM, then print the counters as JSON.")
    parser.add_argument("kind", choices=("udp", "tcp"))
    parser.add_argument("--target", type=_host_port, required=True, help="HOST:PORT")
    parser.add_argument("--listen", type=_host_port, default=("127.0.0.1", 0), help="HOST:PORT")
    parser.add_argument("--preset", choices=sorted(PRESETS), help="start from a named profile")
    for field in dataclasses.fields(Profile):
        kind = {"reorder": int, "seed": str}.get(field.name, float)
        parser.add_argument(f"--{field.name}", type=kind, help=f"override {field.name}")
    args = parser.parse_args(argv)
    profile = PRESETS[args.preset] if args.preset else Profile()
    changes = {f.name: getattr(args, f.name) for f in dataclasses.fields(Profile)
               if getattr(args, f.name) is not None}
    for name in ("burst", "mtu", "queue"):
        if name in changes:
            changes[name] = int(changes[name])
    if "reorder" in changes:
        changes["reorder"] = bool(changes["reorder"])
    profile = dataclasses.replace(profile, **changes)
    relay_class = UdpRelay if args.kind == "udp" else TcpRelay
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    with relay_class(profile, args.target, args.listen) as relay:
        host, port = relay.address
        print(f"{args.kind} {host}:{port} -> {args.target[0]}:{args.target[1]} "
              f"{dataclasses.asdict(profile)}", flush=True)
        stop.wait()
    counters = {"up": dataclasses.asdict(relay.up), "down": dataclasses.asdict(relay.down)}
    print(json.dumps(counters), flush=True)
    return 0
