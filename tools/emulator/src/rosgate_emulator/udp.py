"""A UDP relay through an emulated link, both ways (:class:`UdpRelay`)."""

from __future__ import annotations

import heapq
import itertools
import selectors
import socket
import struct
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

from .relay import SOCKET_BUFFER, Relay, close_quietly, family
from .shaping import IP_HEADER, MAX_UDP_PAYLOAD, UDP_HEADER, Link, Profile, ip_fragments


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



class _UdpDirection:
    def __init__(self, relay: UdpRelay, name: str, sock: socket.socket):
        self.relay = relay
        self.link = Link(relay.profile, name)
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


class UdpRelay(Relay):
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
            self._outer = socket.socket(family(listen[0]), socket.SOCK_DGRAM)
            self._inner = socket.socket(family(self.target[0]), socket.SOCK_DGRAM)
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
            close_quietly(self._wake_r)
            close_quietly(self._wake_w)
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
        close_quietly(self._outer)
        close_quietly(self._inner)
