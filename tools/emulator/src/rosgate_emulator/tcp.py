"""A TCP relay through an emulated link: order kept, losses repaired by retransmission after a
timeout, backpressure when the queue is full (:class:`TcpRelay`)."""

from __future__ import annotations

import selectors
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass

from .relay import JOIN_TIMEOUT, Relay, close_quietly, family, shutdown_quietly
from .shaping import IP_HEADER, TCP_HEADER, Link, Profile


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
        self.link = Link(relay.profile, name)
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
            shutdown_quietly(sock)

    def thread_done(self) -> None:
        with self.relay._lock:
            self._running -= 1
            last = self._running == 0
            if last:
                self.relay._connections.discard(self)
                self.relay._changed.notify_all()
        if last:
            for sock in self.sockets:
                close_quietly(sock)


class TcpRelay(Relay):
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
        self._listener = socket.socket(family(listen[0]), socket.SOCK_STREAM)
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(listen)
            self._listener.listen(64)
        except BaseException:
            self._close_sockets()
            close_quietly(self._wake_r)
            close_quietly(self._wake_w)
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
                        close_quietly(client)
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
                            close_quietly(client)
                            close_quietly(upstream)
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
        close_quietly(self._listener)
