"""One stream connection (TCP, RFCOMM, a Noise channel over either) as a link: its frames written
as stream records — one length-prefixed record, or chunks of one message when long (formats:
:mod:`rosgate.wire.framing`) — through the link's scheduler, as a datagram link's are
(:mod:`rosgate.links`); read back by a thread of its own (:class:`StreamReader`), held to what an
untrusted connection may do until its owner trusts it.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import suppress
from dataclasses import dataclass
from typing import cast

from ..admission import proven
from ..config import LinkConfig
from ..drops import Drop
from ..links.base import POLL, FrameHandler, Link, LostHandler, Sender
from ..links.datagram import SENT_INLINE, _Sending
from ..scheduler import Due, Outgoing
from ..transport import Address, StreamConnection
from ..warn import BUGS
from ..wire.envelope import is_control
from ..wire.framing import (
    CHUNK,
    CHUNK_HEAD,
    CHUNK_LENGTH,
    CHUNKED,
    DEFAULT_MAX_MESSAGE,
    DIRECT_ABOVE,
    EARN_BUFFER,
    LAST,
    LENGTH,
    MAX_OPEN_MESSAGES,
    FramingError,
)

log = logging.getLogger("rosgate")

WRITE = 64 * 1024  # bytes a stream link's writer gathers into one write, at most


def length_prefixed(frame: bytes) -> bytes:
    return LENGTH.pack(len(frame)) + frame


def stream_records(frame: bytes, message: int, chunk: int = CHUNK) -> list[bytes]:
    """``frame`` as the records of a stream: one, or chunks of ``message`` when it is longer
    than ``chunk``."""
    if len(frame) <= chunk:
        return [length_prefixed(frame)]
    view = memoryview(frame)
    starts = range(0, len(frame), chunk)
    last = starts[-1]
    return [CHUNK_HEAD.pack(CHUNKED | (LAST if start == last else 0)
                            | (min(chunk, len(frame) - start) + 4), message & 0xFFFFFFFF)
            + view[start:start + chunk] for start in starts]


class StreamReader:
    """Cuts a byte stream into frames, chunked ones put back together: :meth:`feed` it what the
    connection gives. With ``direct``, a frame longer than :data:`DIRECT_ABOVE` is read straight
    into a buffer of its own once 1/:data:`EARN_BUFFER` of it has come (a length prefix alone
    does not make the reader zero 64 MiB): while :meth:`target` is not None, the caller reads
    into it and says how many bytes came (:meth:`filled`), saving a copy of large frames."""

    def __init__(self, max_frame: int = DEFAULT_MAX_MESSAGE, direct: bool = False):
        self.max_frame = max_frame
        self.direct = direct
        self._buffer = bytearray()
        self._open: dict[int, bytearray] = {}  # message -> what came of it
        self._open_bytes = 0
        self._frame: bytearray | None = None  # a large frame being read into place
        self._filled = 0

    def target(self) -> memoryview | None:
        """Where the next bytes go when a large frame is being read in place, else None."""
        return None if self._frame is None else memoryview(self._frame)[self._filled:]

    def filled(self, count: int) -> bytearray | None:
        """``count`` bytes were read into :meth:`target`; the frame once it is whole."""
        self._filled += count
        frame = self._frame
        if frame is None or self._filled < len(frame):
            return None
        self._frame = None
        return frame

    def feed(self, data: bytes | memoryview) -> Iterator[bytes]:
        """Yield every complete frame; raise FramingError when a length is impossible."""
        buffer = self._buffer
        buffer += data
        start = 0
        try:
            while len(buffer) - start >= 4:
                (length,) = LENGTH.unpack_from(buffer, start)
                chunked = length & CHUNKED
                size = length & CHUNK_LENGTH if chunked else length
                if size > self.max_frame or chunked and size < 4:
                    raise FramingError(f"frame length {size} over the limit {self.max_frame}"
                                       if size > self.max_frame else "a chunk without its head")
                end = start + 4 + size
                if end > len(buffer):
                    have = len(buffer) - start - 4
                    if (self.direct and not chunked and size > DIRECT_ABOVE
                            and have * EARN_BUFFER >= size):
                        # the rest is read straight into the frame's own buffer
                        self._frame = frame = bytearray(size)
                        frame[:have] = memoryview(buffer)[start + 4:]
                        self._filled = have
                        start = len(buffer)
                    break
                if not chunked:
                    yield bytes(buffer[start + 4:end])
                else:
                    whole = self._chunk(buffer, start + 4, end, bool(length & LAST))
                    if whole is not None:
                        yield cast(bytes, whole)  # bytes-like: handlers take either
                start = end
        finally:
            del buffer[:start]

    def _chunk(self, buffer: bytearray, start: int, end: int, last: bool) -> bytearray | None:
        (message,) = LENGTH.unpack_from(buffer, start)
        part = self._open.get(message)
        if part is None:
            if len(self._open) >= MAX_OPEN_MESSAGES:
                raise FramingError(f"more than {MAX_OPEN_MESSAGES} chunked frames open at once")
            part = self._open[message] = bytearray()
        part += buffer[start + 4:end]
        self._open_bytes += end - start - 4
        if len(part) > self.max_frame or self._open_bytes > 2 * self.max_frame:
            raise FramingError(f"chunked frames over the limit {self.max_frame}")
        if not last:
            return None
        del self._open[message]
        self._open_bytes -= len(part)
        return part  # its own buffer, the handler's to keep (and cut: routes do)


@dataclass(frozen=True)
class Untrusted:
    """What a connection may do before its owner trusts it (``bridge.limits``): frames of at most
    ``max_frame`` bytes, and ``deadline`` seconds to earn trust before it is closed."""

    max_frame: int
    deadline: float


class StreamLink(_Sending, Link):
    """One stream connection. The writer takes at most :data:`WRITE` bytes at a time from the
    scheduler, so a frame of a higher class (a Twist behind a camera's backlog) waits for one
    write, not for the whole backlog. When nothing waits, frames are written from the caller's
    thread as far as the connection takes them without waiting (``send_nowait``: no hand-off).

    With ``untrusted``, the connection is held to those limits until :meth:`trust` (a frame too
    long is a corrupt stream; the deadline passing ends it, counted ``handshake_timeout``)."""

    def __init__(self, connection: StreamConnection, name: str, peer: Address,
                 on_frame: FrameHandler, on_lost: LostHandler,
                 on_close: Callable[[StreamLink], None] | None = None,
                 on_closing: Callable[[StreamLink], None] | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024,
                 max_message: int = DEFAULT_MAX_MESSAGE,
                 untrusted: Untrusted | None = None, budget: LinkConfig | None = None,
                 on_control: FrameHandler | None = None):
        self.connection = connection
        self.peer = peer
        self.on_frame = on_frame
        #: a main line's: its control frames go here, the others to ``on_frame``
        self.on_control = on_control
        self.on_lost = on_lost
        self.on_close = on_close
        self.on_closing = on_closing
        # for liveness: the main line's roles set it on every control message (a heartbeat), not
        # on bytes, so a stream that lost its frame boundaries does not look alive
        self.last_heard = time.monotonic()
        self.why = ""  # why the connection ended, once it has
        self._send_nowait = getattr(connection, "send_nowait", None)
        self._messages = itertools.count(1)  # numbers of chunked frames
        self._init_sending(name, budget, 0, CHUNK + CHUNK_HEAD.size, queue_frames,
                           queue_bytes)
        self._reader = StreamReader(untrusted.max_frame if untrusted else max_message,
                                            direct=hasattr(connection, "receive_into"))
        self.max_message = max_message
        self._trust_by = time.monotonic() + untrusted.deadline if untrusted else None
        self._start()

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        # the limits count a frame with its length prefix, as it is written
        if len(frame) <= CHUNK:
            record = length_prefixed(frame)
            if self._send_nowait is not None:
                sent = self._send_now(record, sender, None)
                if sent is not None:
                    return sent
            return self._put(Outgoing(sender, None, len(record), _one(record), time.monotonic()))
        return self._put(Outgoing(sender, None, len(frame) + LENGTH.size,
                                  lambda: stream_records(frame, next(self._messages)),
                                  time.monotonic()))

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Frames of one sender together (a route's backlog): one write from the caller's
        thread when nothing waits; otherwise each is queued."""
        if len(frames) < 2 or self._send_nowait is None or max(map(len, frames)) > CHUNK:
            return sum(self.send(frame, sender) for frame in frames)
        records = [length_prefixed(frame) for frame in frames]
        data = b"".join(records)
        with self._lock:
            go = self._claim(None, len(data))
        if not go:
            now = time.monotonic()
            return sum(self._put(Outgoing(sender, None, len(record), _one(record), now))
                       for record in records)
        try:
            self._send_due(Due(data, None, sender, SENT_INLINE, frames=len(records)))
        finally:
            self._release()
        return len(records)

    def _send_due(self, due: Due) -> bool:
        """Write ``due``'s records as far as the connection takes them now; the rest goes first
        when the writer next writes (nothing comes between: this thread has the turn), and its
        frames are counted out with it."""
        assert self._send_nowait is not None
        try:
            written = self._send_nowait(due.packet)
        except OSError as exc:
            for _ in range(due.frames):
                due.sender.drop(Drop.LINK_DOWN, f"{self.name}: send failed")
            self.fail(f"send failed: {exc}")
            return False
        counters = self.counters
        if written:
            counters.packets_out += 1
            counters.bytes_out += written
        if written == len(due.packet):
            counters.frames_out += due.frames
            if due.frames > 1:
                counters.coalesced_out += due.frames
        else:
            rest = Due(due.packet[written:], None, due.sender, SENT_INLINE, frames=due.frames)
            with self._lock:
                self._rest = rest
        due.sender.on_wire(written, False)
        return True

    def _send_loop(self) -> None:
        """Gather what the scheduler lets go, up to :data:`WRITE` bytes, into one write."""
        wake, closed, scheduler, counters = self._wake, self.closed, self.scheduler, self.counters
        while True:
            batch: list[Due] = []
            size = 0
            with wake:
                while not batch:
                    if closed.is_set():
                        return
                    if self._busy:  # a caller is writing: its rest, if any, comes first
                        wake.wait()
                        continue
                    if self._rest is not None:
                        batch.append(self._rest)
                        size, self._rest = len(self._rest.packet), None
                    due = scheduler.next()
                    while isinstance(due, Due):
                        batch.append(due)
                        size += len(due.packet)
                        if size >= WRITE:
                            break
                        due = scheduler.next()
                    if not batch:
                        wake.wait(max(0.0, due - time.monotonic())
                                  if isinstance(due, float) else None)
                self._busy = True
            if scheduler.dropped:
                self._count_drops()
            try:
                self.connection.send(b"".join([d.packet for d in batch]))
            except OSError as exc:
                for due in batch:
                    if due.ends is not None:
                        due.sender.drop(Drop.LINK_DOWN, f"{self.name}: send failed")
                self.fail(f"send failed: {exc}")
                return
            counters.packets_out += 1
            counters.bytes_out += size
            frames = 0
            for due in batch:
                if due.ends is not None:
                    frames += due.frames
                due.sender.on_wire(len(due.packet), False)
            counters.frames_out += frames
            if frames > 1:
                counters.coalesced_out += frames
            with wake:
                self._busy = False
                wake.notify_all()  # for drain()

    def drain(self, timeout: float) -> bool:
        """Wait until everything sent so far is written (a last word before closing)."""
        with self._wake:
            return self._wake.wait_for(
                lambda: (self.scheduler.idle and not self._busy and self._rest is None
                         or self.closed.is_set()), timeout)

    def _deliver(self, frame: bytes, source: Address) -> None:
        """Hand a frame to its handler (a control frame to ``on_control``, when there is one);
        one that raises has a bug: counted, and the link goes on."""
        on_control = self.on_control
        handler = on_control if on_control is not None and is_control(frame) else self.on_frame
        try:
            handler(frame, self, source)
        except Exception:
            BUGS.bug("handler_error", f"{self.name}: error while handling a frame from {source} "
                                      "(a bug: please report it)")
            self.on_lost(None, Drop.HANDLER_ERROR)

    def trust(self) -> None:
        """The connection proved itself: the full frame size, no deadline, and its place in
        the connection limits is never given up to a newer connection."""
        self._reader.max_frame = self.max_message
        self._trust_by = None
        proven(self.connection)

    @property
    def trusted(self) -> bool:
        return self._trust_by is None

    def _receive_loop(self) -> None:
        receive_into = getattr(self.connection, "receive_into", None)
        buffer = memoryview(bytearray(256 * 1024))
        reader, closed, counters = self._reader, self.closed, self.counters
        while not closed.is_set():
            target = reader.target() if receive_into is not None else None
            try:
                if receive_into is None:
                    got: int | bytes | None = self.connection.receive(len(buffer), POLL)
                else:  # a large frame in place
                    got = receive_into(buffer if target is None else target, POLL)
            except OSError as exc:
                self.fail(f"receive failed: {exc}")
                return
            except Exception as exc:  # a transport plugin's bug: drop this connection, loudly
                BUGS.bug("transport_error", f"{self.name}: the transport's receive failed "
                                            "(a bug in the plugin)")
                self.on_lost(None, Drop.TRANSPORT_ERROR)
                self.fail(f"transport error: {type(exc).__name__}: {exc}")
                return
            trust_by = self._trust_by
            if trust_by is not None and time.monotonic() > trust_by:
                self.on_lost(None, Drop.HANDSHAKE_TIMEOUT)
                self.fail("no handshake in time")
                return
            if got is None:
                continue
            if not got:
                self.fail("closed by peer")
                return
            counters.packets_in += 1
            if target is not None:
                assert isinstance(got, int)
                target.release()  # the frame is the handler's: it may cut it (routes do)
                counters.bytes_in += got
                whole = reader.filled(got)
                if whole is not None:
                    counters.frames_in += 1
                    # its own buffer, the handler's to keep (typed bytes: see DatagramLink)
                    self._deliver(cast(bytes, whole), self.peer)
                continue
            data = buffer[:got] if isinstance(got, int) else got
            counters.bytes_in += len(data)
            count = 0
            try:
                for frame in reader.feed(data):
                    count += 1
                    self._deliver(frame, self.peer)
            except FramingError as exc:
                # a corrupt length means we can no longer find frame boundaries: start afresh
                self.on_lost(None, Drop.BAD_LENGTH)
                self.fail(f"stream corrupt ({exc})")
                return
            finally:
                counters.frames_in += count
                if count > 1:
                    counters.coalesced_in += count

    def fail(self, why: str) -> None:
        """End the connection for a reason worth logging (lost, corrupt, silent)."""
        if self.closed.is_set():
            return
        self.why = why
        # a stranger's connection (never trusted) is counted by its reason, not logged: a
        # flood of them must not flood the log
        log.log(logging.INFO if self.trusted else logging.DEBUG,
                "%s: connection to %s ended: %s", self.name, self.peer, why)
        self.close()

    def _close_io(self) -> None:
        with suppress(OSError):
            self.connection.close()


def _one(packet: bytes) -> Callable[[], list[bytes]]:
    return lambda: [packet]
