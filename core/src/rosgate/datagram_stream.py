"""A byte stream over a datagram link, for the handshake line of peers whose only link to each
other keeps message boundaries and may lose frames (a serial line, a telemetry radio): what
the Noise handshake, the session's keys and the heartbeats need is an ordered, reliable stream.

Stop and wait, the least that is sound on a line that carries a handshake and a ping a second:
each piece carries a sequence number and is sent again until the far side acknowledges it, or
:data:`GIVE_UP` seconds have passed (then ``send`` raises ``OSError`` and the core makes the
line again). A connection is named by a random id chosen by the side that connects, so a piece
of a connection that is gone is never taken into a new one. Nothing here is trusted: the
stream carries the Noise handshake and then its channel, which authenticates every byte; a
forged piece only spoils the line, which is then made again.

Piece: kind (1 byte) + connection id (4) + sequence number (4, big-endian) + bytes.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from collections.abc import Callable
from functools import partial

from .transport import (
    Address,
    DatagramEndpoint,
    DatagramTransport,
    StreamConnection,
    StreamListener,
    StreamTransport,
)

DATA, ACK, CLOSE = b"D", b"A", b"C"
HEAD = struct.Struct("!cII")
#: seconds before the first repetition of a piece, when the link does not say how fast it is
FIRST_WAIT = 0.2
#: the longest wait between repetitions
LONGEST_WAIT = 1.0
#: seconds a piece is repeated before the connection is taken for lost
GIVE_UP = 5.0
#: the receiving thread's wait per look
POLL = 0.2


class DatagramStream(StreamTransport):
    """``transport``'s datagram endpoints as stream connections (one endpoint per connecting
    side; a listener's connections share its endpoint)."""

    def __init__(self, transport: DatagramTransport):
        self.datagrams = transport
        self.name = transport.name  # type: ignore[misc]  # an instance's, not a class's
        self.options = transport.options
        frame = transport.max_frame or 1200
        self.piece = frame - HEAD.size
        # a piece and its acknowledgement on the line, twice over, and a margin
        rate = transport.bandwidth
        self.first_wait = FIRST_WAIT if not rate else FIRST_WAIT + 4 * 8 * frame / rate

    def check_address(self, address: Address) -> Address:
        return self.datagrams.check_address(address)

    def source_hosts(self, host: str) -> frozenset[str] | None:
        return self.datagrams.source_hosts(host)

    def listen(self, address: Address) -> StreamListener:
        return Listener(self, self.datagrams.bind(address))

    def connect(self, address: Address, timeout: float) -> StreamConnection:
        endpoint = self.datagrams.bind((address[0], 0))
        ident = int.from_bytes(os.urandom(4), "big")
        connection = Connection(self, endpoint.send, address, ident, endpoint.close)
        threading.Thread(target=_read, args=(endpoint, connection.take, connection.gone),
                         name=f"{self.name} stream->{address[1]}", daemon=True).start()
        try:
            connection.send(b"", timeout)  # the far side answers: it is there
        except OSError:
            connection.close()
            raise
        return connection


def _read(endpoint: DatagramEndpoint, take: Callable[[bytes, Address], None],
          gone: threading.Event) -> None:
    while not gone.is_set():
        try:
            got = endpoint.receive(POLL)
        except OSError:
            if gone.wait(POLL):
                return
            continue
        if got is not None and len(got[0]) >= HEAD.size:
            take(*got)


class Connection:
    """One stream: sends a piece at a time and waits for its acknowledgement; takes the far
    side's pieces in order."""

    def __init__(self, stream: DatagramStream, send: Callable[[bytes, Address], None],
                 far: Address, ident: int, release: Callable[[], None]):
        self.stream, self._send, self.far, self.ident = stream, send, far, ident
        self._release = release
        self.gone = threading.Event()
        self._ready = threading.Condition()
        self._received = bytearray()
        self._expected = 0  # the far side's next piece
        self._next = 0  # this side's next piece
        self._acked = -1
        self._writing = threading.Lock()

    # -- sending --------------------------------------------------------------------------------
    def send(self, data: bytes, give_up: float = GIVE_UP) -> None:
        with self._writing:
            for start in range(0, max(len(data), 1), self.stream.piece):
                self._piece(data[start:start + self.stream.piece], give_up)

    def _piece(self, data: bytes, give_up: float) -> None:
        seq, self._next = self._next, self._next + 1
        piece = HEAD.pack(DATA, self.ident, seq) + data
        wait, deadline = self.stream.first_wait, time.monotonic() + give_up
        with self._ready:
            while self._acked < seq:
                if self.gone.is_set():
                    raise ConnectionResetError("the stream was closed")
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no answer on {self.stream.name} to {self.far} for "
                                       f"{give_up:.1f} s")
                self._out(piece)
                self._ready.wait(wait)
                wait = min(2 * wait, LONGEST_WAIT)

    def _out(self, piece: bytes) -> None:
        try:
            self._send(piece, self.far)
        except OSError:
            pass  # the line is down for now: the piece is sent again until GIVE_UP

    # -- receiving ------------------------------------------------------------------------------
    def take(self, piece: bytes, source: Address) -> None:
        """A piece from the line (the listener checked the id; a connecting side checks here)."""
        kind, ident, seq = HEAD.unpack_from(piece)
        if ident != self.ident:
            return
        with self._ready:
            if kind == ACK:
                self._acked = max(self._acked, seq)
            elif kind == CLOSE:
                self.gone.set()
            elif kind == DATA:
                if seq == self._expected:
                    self._received += piece[HEAD.size:]
                    self._expected += 1
                if seq < self._expected:  # new, or again because its acknowledgement was lost
                    self._out(HEAD.pack(ACK, self.ident, seq))
            self._ready.notify_all()

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        with self._ready:
            if not self._received and not self.gone.is_set():
                self._ready.wait(timeout)
            if self._received:
                data = bytes(self._received[:max_bytes])
                del self._received[:max_bytes]
                return data
            return b"" if self.gone.is_set() else None

    def close(self) -> None:
        if not self.gone.is_set():
            self._out(HEAD.pack(CLOSE, self.ident, 0))  # once: the far side's repetitions,
            self.gone.set()  # else, tell it soon enough
            with self._ready:
                self._ready.notify_all()
            self._release()


class Listener:
    """Connections made to one address: a piece 0 of a new id opens one; a piece of an id it
    does not know is answered ``CLOSE``, so a far side that outlived this one makes a new one."""

    def __init__(self, stream: DatagramStream, endpoint: DatagramEndpoint):
        self.stream, self.endpoint = stream, endpoint
        self.connections: dict[tuple[Address, int], Connection] = {}
        self.new: list[tuple[StreamConnection, Address]] = []
        self.closed = threading.Event()
        self._lock = threading.Condition()
        threading.Thread(target=_read, args=(endpoint, self._take, self.closed),
                         name=f"{stream.name} stream listener", daemon=True).start()

    def _take(self, piece: bytes, source: Address) -> None:
        kind, ident, seq = HEAD.unpack_from(piece)
        with self._lock:
            connection = self.connections.get((source, ident))
            if connection is None or connection.gone.is_set():
                if kind != DATA or seq != 0 or connection is not None:
                    if kind != CLOSE:
                        self._answer(HEAD.pack(CLOSE, ident, 0), source)
                    return
                connection = Connection(self.stream, self._answer, source, ident,
                                        partial(self._forget, (source, ident)))
                self.connections[(source, ident)] = connection
                self.new.append((connection, source))
                self._lock.notify_all()
        connection.take(piece, source)

    def _answer(self, piece: bytes, to: Address) -> None:
        try:
            self.endpoint.send(piece, to)
        except OSError:
            pass  # as a lost piece: the far side sends again

    def _forget(self, key: tuple[Address, int]) -> None:
        with self._lock:
            self.connections.pop(key, None)

    def accept(self, timeout: float) -> tuple[StreamConnection, Address] | None:
        with self._lock:
            if not self.new:
                self._lock.wait(timeout)
            return self.new.pop(0) if self.new else None

    def close(self) -> None:
        self.closed.set()
        with self._lock:
            connections = list(self.connections.values())
        for connection in connections:
            connection.close()
        self.endpoint.close()
