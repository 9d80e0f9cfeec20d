"""Links: the core's side of a transport. Framing, fragmentation and threads live here, so a
transport plugin only opens sockets.

* :class:`DatagramLink` — one bound endpoint; sends whole frames, several frames coalesced in
  one datagram, or fragments, from a send thread of its own when the caller should not wait;
  reassembles, splits, and hands every frame to ``on_frame``. A transport with small frames
  (``max_frame`` below ``framing.COMPACT_BELOW``, such as CAN) gets the compact fragment scheme
  instead. In bare mode (``framing: none``) it hands over the datagram untouched.
* :class:`StreamLink` — one connection; frames carry a length prefix. Sending never blocks the
  caller: frames wait in a bounded queue for a writer thread.
* :class:`LinkSlot` — a place for a stream link that comes and goes (reconnects). While it is
  empty, frames of reliable senders wait in a bounded queue and leave in order when a connection
  is attached; frames of other senders are dropped.
* :class:`Connector` — keeps a :class:`LinkSlot` filled: connects, and reconnects after every loss.
* :class:`Acceptor` — accepts stream connections and hands each to ``on_connection``, within
  :class:`ConnectionLimits` and from admitted :class:`Sources` only; it backs off when accepting
  fails (out of file descriptors), never spinning.

Who sent a frame travels with it: every ``send`` takes the :class:`Sender` (a route, or the
control channel) so a frame dropped later — a queue that overflows, a connection that breaks
with frames still queued — is counted against it, without a lookup. Losses on the receiving
side (a fragment that never came) are reported with the topic id the fragments carried.

Every receive loop catches what a peer's bytes can cause and counts it; a link never dies of
input, and an unexpected error's traceback is logged once per reason per minute
(:data:`rosgate.warn.BUGS`). A stream connection the bridge accepted is untrusted until its
owner calls :meth:`StreamLink.trust` (a handshake, a hello): until then its frames are small
and it has a deadline (:class:`Untrusted`). :class:`Lifetime` is what a running bridge closes
when it stops.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import random
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Protocol, cast

from .errors import LinkError
from .transport import Address, DatagramEndpoint, StreamConnection, StreamListener, Transport
from .warn import BUGS, Warner
from .wire import envelope, framing

log = logging.getLogger("rosgate")

FrameHandler = Callable[[bytes, "Link", Address], None]
#: a loss on the receiving side: (topic id when known, reason)
LostHandler = Callable[[int | None, str], None]

POLL = 0.2  # seconds a receive waits before checking whether the link is closing
CONNECT_TIMEOUT = 5.0
_WARNER = Warner()  # for an acceptor whose owner does not count its refusals
ACCEPT_BACKOFF = (0.1, 1.0)  # seconds between failed accepts: the first, doubling up to the second


class Sender(Protocol):
    """What sends a frame: a route, or a role's control channel."""

    @property
    def topic_id(self) -> int:
        """The id fragments of its frames carry (so a receiver counts a lost one against it)."""

    @property
    def reliable(self) -> bool:
        """Its frames wait in a :class:`LinkSlot` while the link is down (reliable QoS)."""

    def drop(self, reason: str, detail: str = "") -> None:
        """Count one of its frames as dropped on the way out."""

    # optional: ``max_wait_ns``, nanoseconds a frame of it may wait in a link's send queue
    # before it is dropped (``too_late``); missing or 0: it waits (reliable topics, control)


def max_wait_ns(sender: Sender) -> int:
    return getattr(sender, "max_wait_ns", 0)


class Link:
    """What a route sends through and what frames are reported from."""

    name: str
    closed: threading.Event
    counters: LinkCounters
    #: datagram links need a destination for every send; stream links are connected
    datagram: bool = False
    #: while a frame is handed to its handler: when the datagram that carried it arrived (ns,
    #: the clock of time.time_ns, as the transport's receive_into says), or 0: unknown
    arrived: int = 0

    # a link implements send or send_all (or both): each defaults to the other

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        """Hand ``frame`` to the link. False when it was dropped at once (counted against
        ``sender``); True when it was sent or queued — a queued frame that is lost later is
        counted against ``sender`` then."""
        return self.send_all([frame], sender, to) == 1

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Hand several frames of one sender to the link at once (they may share a datagram or a
        write); how many were sent or queued, as :meth:`send` says for one."""
        return sum(self.send(frame, sender, to) for frame in frames)

    def close(self) -> None:
        raise NotImplementedError


class Lifetime:
    """What a running bridge closes when it stops, in reverse opening order, and the event that
    says it is stopping. Links that end by themselves (a connection the peer closed) are
    forgotten, so they are not held until the end."""

    def __init__(self) -> None:
        self.stopping = threading.Event()
        self._items: dict[int, Any] = {}
        self._lock = threading.Lock()

    def closing(self, item: Any) -> Any:
        with self._lock:
            self._items[id(item)] = item
        return item

    def forget(self, item: Any) -> None:
        with self._lock:
            self._items.pop(id(item), None)

    def links(self) -> list[Link]:
        """The links open now that count what they carry."""
        with self._lock:
            return [item for item in self._items.values()
                    if isinstance(item, Link) and isinstance(getattr(item, "counters", None),
                                                             LinkCounters)]

    def close_all(self) -> None:
        self.stopping.set()
        with self._lock:
            items = list(self._items.values())
            self._items.clear()
        for item in reversed(items):
            item.close()


@dataclass
class LinkCounters:
    """What a link carried, per direction: frames, the datagrams (or stream writes and reads)
    that carried them, and how many frames shared one with others (coalesced)."""

    frames_out: int = 0
    packets_out: int = 0
    coalesced_out: int = 0
    bytes_out: int = 0
    frames_in: int = 0
    packets_in: int = 0
    coalesced_in: int = 0
    bytes_in: int = 0

    def snapshot(self) -> dict[str, int]:
        return dict(vars(self))

    def line(self) -> str:
        return (f"out {self.frames_out} frames in {self.packets_out} packets "
                f"({self.coalesced_out} coalesced, {self.bytes_out} B), "
                f"in {self.frames_in} frames in {self.packets_in} packets "
                f"({self.coalesced_in} coalesced, {self.bytes_in} B)")


class DatagramLink(Link):
    """A bound datagram endpoint: frames out (whole, coalesced, in fragments or compact pieces),
    datagrams in (reassembled, split), each frame to ``on_frame``.

    Sending: frames that each fit a datagram go out on the caller's thread when the link is
    idle, so a message that comes alone costs no thread hand-off; frames handed over together
    (:meth:`send_all`: a route that found several messages waiting) share datagrams, as many to
    one as ``max_frame`` allows (a batch, see :mod:`rosgate.wire.framing`). A frame that needs
    fragments or compact pieces, and frames sent while another thread is sending, join a
    bounded queue instead, which the link's send thread drains, coalescing what waits for each
    destination the same way. Nothing waits for frames that are not there yet, so coalescing
    adds no latency, and a large frame never holds up the ROS executor.
    """

    datagram = True

    def __init__(self, transport: Transport, endpoint: DatagramEndpoint, name: str,
                 on_frame: FrameHandler, on_lost: LostHandler, bare: bool = False,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE, sources: Sources | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024):
        self.transport = transport
        #: who frames are taken from (None: anyone); others are counted ``not_allowed``
        self.sources = sources
        self.endpoint = endpoint
        self.name = name
        self.bare = bare
        self.max_frame = transport.max_frame
        self.on_frame = on_frame
        self.on_lost = on_lost
        self.closed = threading.Event()
        self.counters = LinkCounters()
        self.queue_frames = queue_frames
        self.queue_bytes = queue_bytes
        # small frames cannot spare 14 bytes of fragment header: every frame goes as compact pieces
        self.compact = not bare and self.max_frame < framing.COMPACT_BELOW
        self.reassembler: framing.Reassembler | framing.CompactReassembler
        if self.compact:
            self.reassembler = framing.CompactReassembler(on_lost, envelope.topic_of,
                                                          max_message=max_message)
        else:
            self.reassembler = framing.Reassembler(on_lost, max_message=max_message)
        self._counters: dict[Address, int] = {}  # compact: the next piece's counter per destination
        self._send_parts = getattr(endpoint, "send_parts", None)
        # the queue, and whether a thread is sending (inline or the send thread): one at a time
        self._queue: deque[tuple[bytes, Sender, Address, int]] = deque()  # ... queued at (ns)
        self._queued_bytes = 0
        self._busy = False
        # entered as the plain lock on the way out (a Condition's own with-statement costs a
        # Python call each way, ~0.3 us); the send thread waits on the condition
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._threads = [
            threading.Thread(target=self._receive_loop, name=f"rx-{name}", daemon=True),
            threading.Thread(target=self._send_loop, name=f"tx-{name}", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        assert to is not None, "a datagram link needs a destination"
        count = len(frames)
        if count == 1:
            total = biggest = len(frames[0])
        elif count:
            sizes = [len(frame) for frame in frames]
            total, biggest = sum(sizes), max(sizes)
        else:
            return 0
        limit = self.max_frame
        if biggest > limit and self.bare:
            return self._too_large_for_bare(frames, sender, to)
        lock, wake = self._lock, self._wake
        with lock:
            if self.closed.is_set():
                verdict = "closed"
            elif biggest <= limit and not self._busy and not self._queue and not self.compact:
                self._busy = True  # this thread sends them; anyone else queues meanwhile
                verdict = "inline"
            elif (len(self._queue) + count > self.queue_frames
                  or self._queued_bytes + total > self.queue_bytes):
                verdict = "full"
            else:
                now = time.monotonic_ns()
                self._queue.extend([(frame, sender, to, now) for frame in frames])
                self._queued_bytes += total
                if not self._busy:
                    wake.notify()
                return count
        if verdict == "inline":
            try:
                if count == 1:
                    failed = 0 if self._send_one(frames[0], sender, to) else 1
                else:
                    failed = self._transmit([(frame, sender, to, 0) for frame in frames])
            finally:
                with lock:
                    self._busy = False
                    if self._queue:
                        wake.notify()
            return count - failed
        for _ in frames:
            if verdict == "closed":
                sender.drop("link_down", f"{self.name} is closed")
            else:
                sender.drop("queue_full", f"{self.name} has {self.queue_frames} frames or "
                                          f"{self.queue_bytes} bytes waiting to be sent")
        return 0

    def _too_large_for_bare(self, frames: list[bytes], sender: Sender, to: Address) -> int:
        """A bare link's receiver takes one message per datagram: a longer one is dropped."""
        fitting = []
        for frame in frames:
            if len(frame) > self.max_frame:
                sender.drop("too_large_for_bare_framing",
                            f"{len(frame)} bytes, {self.name} carries at most {self.max_frame}")
            else:
                fitting.append(frame)
        return self.send_all(fitting, sender, to) if fitting else 0

    def _send_one(self, frame: bytes, sender: Sender, to: Address) -> bool:
        try:
            self.endpoint.send(frame, to)
        except OSError as exc:
            sender.drop("send_error", f"to {to} on {self.name}: {exc}")
            return False
        counters = self.counters
        counters.frames_out += 1
        counters.packets_out += 1
        counters.bytes_out += len(frame)
        return True

    def _send_loop(self) -> None:
        wake, closed = self._wake, self.closed
        while True:
            with wake:
                if self._busy:  # this thread's own, from the turn before
                    self._busy = False
                while not self._queue or self._busy:
                    if closed.is_set():
                        return
                    wake.wait()
                queued, self._queue = self._queue, deque()
                self._queued_bytes = 0
                self._busy = True
            try:
                self._transmit(queued)
            except Exception:  # a bug; the link must keep sending
                log.exception("%s: error while sending (a bug: please report it)", self.name)

    def _transmit(self, queued: Iterable[tuple[bytes, Sender, Address, int]]) -> int:
        """Send frames in order per destination: frames that fit together share a datagram
        (not on bare links, whose receivers take one message per datagram); a large frame goes
        in fragments (or compact pieces). A frame queued (at a time other than 0) longer than
        its sender's ``max_wait_ns`` is dropped instead (``too_late``). How many could not be
        sent (counted)."""
        groups: dict[Address, list] = {}  # destination -> [total frame bytes, (frame, sender)...]
        limit, coalesce, failed = self.max_frame, not self.bare, 0
        now = time.monotonic_ns()
        for frame, sender, to, queued_at in queued:
            if queued_at and now - queued_at > max_wait_ns(sender) > 0:
                sender.drop("too_late", f"waited {(now - queued_at) / 1e6:.0f} ms to be sent "
                                        f"on {self.name}")
                failed += 1
                continue
            size = len(frame)
            if self.compact or size > limit:
                group = groups.pop(to, None)
                if group is not None:
                    failed += self._send_group(to, group)
                failed += not self._send_large(frame, sender, to)
                continue
            group = groups.get(to)
            if group is None:
                groups[to] = [size, (frame, sender)]
            elif not coalesce or framing.batch_size(group[0] + size, len(group)) > limit:
                failed += self._send_group(to, group)
                groups[to] = [size, (frame, sender)]
            else:
                group[0] += size
                group.append((frame, sender))
        for to, group in groups.items():
            failed += self._send_group(to, group)
        return failed

    def _send_group(self, to: Address, group: list) -> int:
        frames = group[1:]
        if len(frames) == 1:
            return 0 if self._send_one(frames[0][0], frames[0][1], to) else 1
        try:
            parts = framing.batch([frame for frame, _ in frames])
            if self._send_parts is not None:
                self._send_parts(parts, to)
            else:
                self.endpoint.send(b"".join(parts), to)
        except OSError as exc:
            for _, sender in frames:
                sender.drop("send_error", f"to {to} on {self.name}: {exc}")
            return len(frames)
        counters = self.counters
        counters.frames_out += len(frames)
        counters.packets_out += 1
        counters.bytes_out += group[0]
        counters.coalesced_out += len(frames)
        return 0

    def _send_large(self, frame: bytes, sender: Sender, to: Address) -> bool:
        """A frame in fragments, or in compact pieces (on a link of small frames, every frame)."""
        try:
            if self.compact:
                counter = self._counters.get(to, 0)  # only this thread sends compact pieces
                pieces = framing.compact_fragment(frame, self.max_frame, counter)
                self._counters[to] = (counter + len(pieces)) & framing.COMPACT_COUNTER
                for piece in pieces:
                    self.endpoint.send(piece, to)
                sent = len(pieces)
            else:
                frame_id = int.from_bytes(os.urandom(4), "big")  # unpredictable: see Reassembler
                parts = framing.fragments(frame, self.max_frame, sender.topic_id, frame_id)
                send_parts = self._send_parts
                for header, chunk in parts:
                    if send_parts is not None:
                        send_parts([header, chunk], to)
                    else:
                        self.endpoint.send(header + chunk, to)
                sent = len(parts)
        except (OSError, framing.FramingError) as exc:
            sender.drop("send_error", f"to {to} on {self.name}: {exc}")
            return False
        counters = self.counters
        counters.frames_out += 1
        counters.packets_out += sent
        counters.bytes_out += len(frame)
        return True

    def _receive_loop(self) -> None:
        receive_into = getattr(self.endpoint, "receive_into", None)
        if receive_into is None:
            receive: Callable[[], tuple[bytes | memoryview, Address] | None] = \
                lambda: self.endpoint.receive(POLL)
        else:
            # one buffer for every datagram: longer than any frame this link accepts, so a
            # datagram that fills it is one too long
            buffer = memoryview(bytearray(max(self.max_frame, 65_535) + 1))

            def receive() -> tuple[bytes | memoryview, Address] | None:
                got = receive_into(buffer, POLL)
                if got is None:
                    return None
                size, source, self.arrived = got
                if size >= len(buffer):
                    self.on_lost(None, "oversized_datagram")
                    return None
                return buffer[:size], source

        closed = self.closed
        while not closed.is_set():
            try:
                got = receive()
            except OSError:
                if closed.is_set():
                    return
                continue
            except Exception:  # a transport plugin's bug must not silently end the link
                BUGS.bug("transport_error", f"{self.name}: the transport's receive failed "
                                            "(a bug in the plugin)")
                self.on_lost(None, "transport_error")
                closed.wait(POLL)  # do not spin on a receive that fails at once
                continue
            if got is None:
                self.reassembler.expire()
                continue
            self._datagram(*got)

    def _datagram(self, datagram: bytes | memoryview, source: Address) -> None:
        """One datagram as it came (a view of the receive buffer, valid until the next one)."""
        if self.sources is not None and not self.sources.admits(source, datagram):
            self.on_lost(None, "not_allowed")
            return
        counters = self.counters
        counters.packets_in += 1
        counters.bytes_in += len(datagram)
        if self.bare:
            counters.frames_in += 1
            deliver(self, datagram if type(datagram) is bytes else bytes(datagram), source)
            return
        kind = datagram[1] if len(datagram) > 1 and datagram[0] == 0x52 else 0  # "R?"
        if self.compact or kind == 0x46:  # "RF": a fragment
            try:
                frame = self.reassembler.add(source, datagram)
            except framing.FramingError:
                self.on_lost(None, "bad_fragment")
                return
            if frame is not None:
                counters.frames_in += 1
                # the buffer it was reassembled in, the handler's to keep: a route hands it to
                # rclpy without a copy (typed bytes: handlers take any bytes-like frame)
                deliver(self, cast(bytes, frame), source)
        elif kind == 0x42:  # "RB": several frames
            try:
                for record in framing.unbatch(datagram):
                    counters.frames_in += 1
                    counters.coalesced_in += 1
                    deliver(self, bytes(record), source)
            except framing.FramingError:
                self.on_lost(None, "bad_batch")
        else:
            counters.frames_in += 1
            deliver(self, datagram if type(datagram) is bytes else bytes(datagram), source)

    def close(self) -> None:
        with self._wake:
            self.closed.set()
            unsent = [sender for _, sender, _, _ in self._queue]
            self._queue.clear()
            self._queued_bytes = 0
            self._wake.notify_all()
        for sender in unsent:
            sender.drop("link_down", f"{self.name} closed with the frame still queued")
        self.endpoint.close()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(timeout=2)


@dataclass(frozen=True)
class Untrusted:
    """What a connection may do before its owner trusts it (``bridge.limits``): frames of at most
    ``max_frame`` bytes, and ``deadline`` seconds to earn trust before it is closed."""

    max_frame: int
    deadline: float


class StreamLink(Link):
    """One stream connection, framed with length prefixes. With ``untrusted``, it is held to
    those limits until :meth:`trust` (a frame too long is a corrupt stream; the deadline passing
    ends the connection, counted ``handshake_timeout``).

    Sending never blocks the caller: when nothing is being written, frames are written from the
    caller's thread as far as the connection takes them without waiting (``send_nowait``: no
    thread hand-off for a message alone); everything else waits in a bounded queue for the
    link's writer thread, which writes what is queued in one go."""

    def __init__(self, connection: StreamConnection, name: str, peer: Address,
                 on_frame: FrameHandler, on_lost: LostHandler,
                 on_close: Callable[[StreamLink], None] | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE,
                 untrusted: Untrusted | None = None):
        self.connection = connection
        self.name = name
        self.peer = peer
        self.on_frame = on_frame
        self.on_lost = on_lost
        self.on_close = on_close
        self.closed = threading.Event()
        # for liveness: the main line's roles set it on every control message (a heartbeat), not
        # on bytes, so a stream that lost its frame boundaries does not look alive
        self.last_heard = time.monotonic()
        self.why = ""  # why the connection ended, once it has
        self.queue_frames = queue_frames
        self.queue_bytes = queue_bytes
        self.counters = LinkCounters()
        self._send_nowait = getattr(connection, "send_nowait", None)
        self._queue: deque[tuple[bytes, Sender, int]] = deque()  # record, sender, queued at (ns)
        self._queued_bytes = 0
        self._busy = False  # a thread is writing (the caller's, or the writer with a batch)
        self._lock = threading.Lock()  # the plain lock on the way in (see DatagramLink)
        self._wake = threading.Condition(self._lock)
        self._reader = framing.StreamReader(untrusted.max_frame if untrusted else max_message,
                                            direct=hasattr(connection, "receive_into"))
        self.max_message = max_message
        self._trust_by = time.monotonic() + untrusted.deadline if untrusted else None
        self._threads = [
            threading.Thread(target=self._receive_loop, name=f"rx-{name}", daemon=True),
            threading.Thread(target=self._send_loop, name=f"tx-{name}", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        if self.closed.is_set():
            for _ in frames:
                sender.drop("link_down", f"{self.name} is closed")
            return 0
        records = [framing.length_prefixed(frame) for frame in frames]
        size = sum(map(len, records))
        with self._lock:
            if (len(self._queue) + len(records) > self.queue_frames
                    or self._queued_bytes + size > self.queue_bytes):
                verdict = "full"
            elif self._send_nowait is not None and not self._busy and not self._queue:
                self._busy = True  # this thread writes; anyone else queues meanwhile
                verdict = "inline"
            else:
                verdict = "queued"
                now = time.monotonic_ns()
                self._queue.extend([(record, sender, now) for record in records])
                self._queued_bytes += size
                if not self._busy:
                    self._wake.notify()
        if verdict == "full":
            for _ in frames:
                sender.drop("queue_full", f"{self.name} has {self.queue_frames} frames or "
                                          f"{self.queue_bytes} bytes waiting")
            return 0
        if verdict == "inline":
            self._write_now(records, sender)
        return len(frames)

    def _write_now(self, records: list[bytes], sender: Sender) -> None:
        """Write from the caller's thread what goes without waiting; the rest goes first in the
        writer's queue (nothing can come between: this thread is the only one writing)."""
        assert self._send_nowait is not None
        data = records[0] if len(records) == 1 else b"".join(records)
        try:
            written = self._send_nowait(data)
        except OSError as exc:
            with self._lock:
                self._busy = False
            for _ in records:
                sender.drop("link_down", f"{self.name}: send failed")
            self.fail(f"send failed: {exc}")
            return
        self._count_out(records, written, len(data))
        with self._lock:
            if written < len(data):
                now, rest, offset = time.monotonic_ns(), [], 0
                for record in records:  # the frames not wholly written, the first of them cut
                    end = offset + len(record)
                    if end > written:
                        rest.append((record[max(0, written - offset):], sender, now))
                    offset = end
                self._queue.extendleft(reversed(rest))
                self._queued_bytes += len(data) - written
            self._busy = False
            if self._queue:
                self._wake.notify()

    def _count_out(self, records: list[bytes], written: int, size: int) -> None:
        if not written:
            return
        counters = self.counters
        counters.packets_out += 1
        counters.bytes_out += written
        if written == size:
            counters.frames_out += len(records)
            if len(records) > 1:
                counters.coalesced_out += len(records)

    def _send_loop(self) -> None:
        wake = self._wake
        while True:
            with wake:
                if self._busy:  # this thread's own, from the turn before
                    self._busy = False
                    wake.notify_all()  # for drain()
                while (not self._queue or self._busy) and not self.closed.is_set():
                    wake.wait()
                if self.closed.is_set():
                    return
                # one write for everything queued: fewer system calls under load
                batch = list(self._queue)
                self._queue.clear()
                self._queued_bytes = 0
                self._busy = True
            now = time.monotonic_ns()
            if any(max_wait_ns(sender) for _, sender, _ in batch):
                kept = []
                for entry in batch:
                    _, sender, queued_at = entry
                    if now - queued_at > max_wait_ns(sender) > 0:
                        sender.drop("too_late", f"waited {(now - queued_at) / 1e6:.0f} ms to be "
                                                f"sent on {self.name}")
                    else:
                        kept.append(entry)
                batch = kept
                if not batch:
                    continue
            data = b"".join(record for record, _, _ in batch)
            try:
                self.connection.send(data)
            except OSError as exc:
                for _, sender, _ in batch:
                    sender.drop("link_down", f"{self.name}: send failed")
                self.fail(f"send failed: {exc}")
                return
            self._count_out([record for record, _, _ in batch], len(data), len(data))

    def drain(self, timeout: float) -> bool:
        """Wait until everything sent so far is written (a last word before closing)."""
        with self._wake:
            return self._wake.wait_for(
                lambda: not self._queue and not self._busy or self.closed.is_set(), timeout)

    def trust(self) -> None:
        """The connection proved itself: the full frame size, no deadline."""
        self._reader.max_frame = self.max_message
        self._trust_by = None

    @property
    def trusted(self) -> bool:
        return self._trust_by is None

    def _receive_loop(self) -> None:
        receive_into = getattr(self.connection, "receive_into", None)
        buffer = memoryview(bytearray(256 * 1024))
        reader, closed = self._reader, self.closed
        while not closed.is_set():
            target = reader.target() if receive_into is not None else None
            try:
                if receive_into is not None and target is not None:  # a large frame, in place
                    got: int | bytes | None = receive_into(target, POLL)
                elif receive_into is not None:
                    got = receive_into(buffer, POLL)
                else:
                    got = self.connection.receive(len(buffer), POLL)
            except OSError as exc:
                self.fail(f"receive failed: {exc}")
                return
            except Exception as exc:  # a transport plugin's bug: drop this connection, loudly
                BUGS.bug("transport_error", f"{self.name}: the transport's receive failed "
                                            "(a bug in the plugin)")
                self.on_lost(None, "transport_error")
                self.fail(f"transport error: {type(exc).__name__}: {exc}")
                return
            trust_by = self._trust_by
            if trust_by is not None and time.monotonic() > trust_by:
                self.on_lost(None, "handshake_timeout")
                self.fail("no handshake in time")
                return
            if got is None:
                continue
            if not got:
                self.fail("closed by peer")
                return
            counters = self.counters
            counters.packets_in += 1
            if target is not None:
                assert isinstance(got, int)
                target.release()  # the frame is the handler's: it may cut it (routes do)
                counters.bytes_in += got
                whole = reader.filled(got)
                if whole is not None:
                    counters.frames_in += 1
                    # its own buffer, the handler's to keep (typed bytes: see DatagramLink)
                    deliver(self, cast(bytes, whole), self.peer)
                continue
            data = buffer[:got] if isinstance(got, int) else got
            counters.bytes_in += len(data)
            count = 0
            try:
                for frame in reader.feed(data):
                    count += 1
                    deliver(self, frame, self.peer)
            except framing.FramingError as exc:
                # a corrupt length means we can no longer find frame boundaries: start afresh
                self.on_lost(None, "bad_length")
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

    def close(self) -> None:
        with self._wake:  # once only, whichever thread gets here first
            if self.closed.is_set():
                return
            self.closed.set()
            self._wake.notify_all()
        try:
            self.connection.close()
        except OSError:
            pass
        for thread in self._threads:
            # the receive thread may fail before the send thread has even started; an unstarted
            # thread sees `closed` when it starts and returns
            if thread is not threading.current_thread() and thread.ident is not None:
                thread.join(timeout=2)
        with self._wake:  # what never reached the connection is a drop, and counted as one
            unsent = [sender for _, sender, _ in self._queue]
            self._queue.clear()
            self._queued_bytes = 0
        for sender in unsent:
            sender.drop("link_down", f"{self.name} closed with the frame still queued")
        if self.on_close:
            self.on_close(self)


@dataclass(frozen=True)
class QueueLimits:
    """How much a :class:`LinkSlot` holds for reliable topics while it has no connection."""

    frames: int
    bytes: int


class LinkSlot(Link):
    """A stream link that comes and goes. A :class:`Connector` (or a server that accepted the
    peer again) :meth:`attach`-es each new connection.

    While there is no live connection, frames of :attr:`Sender.reliable` senders wait, oldest
    dropped first when the limits are reached (counted ``queue_overflow``), and are handed to the
    next connection in order, before anything sent later. Other frames are counted ``link_down``.
    Frames already handed to a connection that then fails are not taken back (there are no
    acknowledgements): a connection's loss can cost what was in flight.
    """

    def __init__(self, name: str, limits: QueueLimits):
        self.name = name
        self.limits = limits
        self.current: StreamLink | None = None
        self.closed = threading.Event()
        self._waiting: deque[tuple[bytes, Sender]] = deque()
        self._waiting_bytes = 0
        self._lock = threading.Lock()  # keeps sends and the flush of the queue in order

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        overflow: list[Sender] = []
        with self._lock:
            link = self.current
            if link is not None and not link.closed.is_set():
                return link.send_all(frames, sender)
            if self.closed.is_set() or not sender.reliable:
                refused = True
            else:
                refused = False
                for frame in frames:
                    self._waiting.append((frame, sender))
                    self._waiting_bytes += len(frame)
                while self._waiting and (len(self._waiting) > self.limits.frames
                                         or self._waiting_bytes > self.limits.bytes):
                    old, old_sender = self._waiting.popleft()
                    self._waiting_bytes -= len(old)
                    overflow.append(old_sender)
        for old_sender in overflow:
            old_sender.drop("queue_overflow", f"{self.name} is down and its queue is full")
        if refused:
            for _ in frames:
                sender.drop("link_down", f"{self.name} is down")
            return 0
        return len(frames)

    def attach(self, link: StreamLink) -> None:
        """Use ``link`` from now on; what waited goes first."""
        with self._lock:
            while self._waiting:
                frame, sender = self._waiting.popleft()
                link.send(frame, sender)
            self._waiting_bytes = 0
            self.current = link

    def discard(self, reason: str) -> None:
        """Drop what waits (its topic ids mean nothing to a new session), counted by ``reason``."""
        with self._lock:
            senders = [sender for _, sender in self._waiting]
            self._waiting.clear()
            self._waiting_bytes = 0
        for sender in senders:
            sender.drop(reason)

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    @property
    def counters(self) -> LinkCounters:  # type: ignore[override]  # the connection's, read-only
        link = self.current
        return link.counters if link is not None else LinkCounters()

    def close(self) -> None:
        self.closed.set()
        self.discard("link_down")
        if self.current is not None:
            self.current.close()


@dataclass(frozen=True)
class Backoff:
    """Seconds between reconnection attempts: from ``min``, doubling up to ``max``, jittered."""

    min: float
    max: float

    def delay(self, failures: int) -> float:
        return min(self.min * 2 ** (failures - 1), self.max) * random.uniform(0.5, 1.0)


class Connector:
    """Keeps a stream connection up: connects, and after every loss reconnects by itself.

    Attempts are spaced by capped exponential backoff with jitter, so a fleet of clients does
    not hammer a server that comes back. After a connection that worked is lost, the next
    attempt is immediate. ``on_connected(link)`` may refuse a connection (a failed handshake),
    which counts as a failed attempt; ``on_lost(link)`` hears of every accepted connection that
    ended.
    """

    def __init__(self, transport: Transport, address: Address, slot: LinkSlot,
                 on_frame: FrameHandler, on_frame_lost: LostHandler, life: Lifetime,
                 backoff: Backoff,
                 on_connected: Callable[[StreamLink], bool] | None = None,
                 on_lost: Callable[[StreamLink], None] | None = None,
                 secure: Callable[[StreamConnection], StreamConnection] | None = None):
        self.transport = transport
        self.secure = secure
        self.address = address
        self.slot = slot
        self.on_frame = on_frame
        self.on_frame_lost = on_frame_lost
        self.life = life
        self.backoff = backoff
        self.on_connected = on_connected
        self.on_lost = on_lost
        self.connected = threading.Event()
        self._last_failure = ""
        self._thread = threading.Thread(target=self._loop, name=f"connect-{slot.name}", daemon=True)
        life.closing(self)

    def start(self) -> Connector:
        self._thread.start()
        return self

    def _loop(self) -> None:
        stopping = self.life.stopping
        failures = 0
        while not stopping.is_set() and not self.slot.closed.is_set():
            link = self._connect()
            if link is None:
                failures += 1
                stopping.wait(self.backoff.delay(failures))
                continue
            failures = 0
            self._last_failure = ""
            self.slot.attach(link)
            self.connected.set()
            while not link.closed.wait(0.5):
                if stopping.is_set() or self.slot.closed.is_set():
                    break
            self.connected.clear()
            if stopping.is_set() and not self.slot.closed.is_set():
                return  # the bridge is stopping: its role may have a last word (bye), then
                # closing the slot closes the link
            link.close()
            if self.on_lost is not None and not stopping.is_set():
                self.on_lost(link)

    def _connect(self) -> StreamLink | None:
        """One attempt: a connection its owner accepted, or None."""
        try:
            connection = self.transport.connect(self.address, CONNECT_TIMEOUT)
        except (OSError, LinkError) as exc:
            log.debug("%s: connect failed: %s", self.slot.name, exc)
            return None
        if self.secure is not None:
            try:
                connection = self.secure(connection)
            except LinkError as exc:
                connection.close()
                self.failed(exc)
                return None
        link = self.life.closing(StreamLink(connection, self.slot.name, self.address,
                                            self.on_frame, self.on_frame_lost,
                                            on_close=self.life.forget))
        if self.on_connected is not None and not self.on_connected(link):
            link.close()
            return None
        return link

    def failed(self, exc: LinkError) -> None:
        """A connection that opened but was refused (its handshake failed): said once, until a
        connection works again."""
        if str(exc) != self._last_failure:
            self._last_failure = str(exc)
            log.warning("%s: %s", self.slot.name, exc)

    def close(self) -> None:
        self.slot.close()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=3)


class Sources:
    """Who a link takes frames or connections from: hosts as they appear in a source address,
    and IP networks (``10.0.0.0/24``)."""

    def __init__(self, hosts: Iterable[str], networks: Iterable[str] = ()):
        self.hosts = set(hosts)
        self._seen: dict[str, bool] = {}
        self.networks = []
        for text in networks:
            try:
                self.networks.append(ipaddress.ip_network(text, strict=False))
            except ValueError:
                self.hosts.add(text)  # not an IP network: a host as written (a device address)

    def admits(self, source: Address, datagram: bytes | memoryview = b"") -> bool:
        host = source[0]
        if host in self.hosts:
            return True
        if host.startswith("::ffff:"):  # an IPv4 peer on a dual-stack socket
            host = host[7:]
            if host in self.hosts:
                return True
        if not self.networks:
            return False
        known = self._seen.get(host)
        if known is None:  # parsed once per host: a datagram path's cost stays a dict lookup
            try:
                address = ipaddress.ip_address(host.partition("%")[0])
                known = any(address in network for network in self.networks)
            except ValueError:
                known = False
            if len(self._seen) >= 4096:  # hosts come from the network: bounded
                self._seen.clear()
            self._seen[host] = known
        return known

    def __repr__(self) -> str:
        return ", ".join([*sorted(self.hosts), *map(str, self.networks)]) or "nobody"


class KnownSources(Sources):
    """Sources learnt while running: a server's clients, at the addresses their genuine hellos
    came from. A datagram from anywhere else is taken only when it is a hello (which the server
    then checks); everything else from there is ``not_allowed``, before any reassembly."""

    def __init__(self) -> None:
        super().__init__(())
        self._known: Counter[Address] = Counter()
        self._lock = threading.Lock()

    def learn(self, source: Address) -> None:
        with self._lock:
            self._known[source] += 1

    def forget(self, source: Address) -> None:
        with self._lock:
            self._known[source] -= 1
            if self._known[source] <= 0:
                del self._known[source]

    def admits(self, source: Address, datagram: bytes | memoryview = b"") -> bool:
        return source in self._known or envelope.is_hello(datagram)

    def __repr__(self) -> str:
        return f"{len(self._known)} client address(es)"


class ConnectionLimits:
    """How many accepted stream connections a bridge holds at once: in total, and from one
    source address (``bridge.limits``). Shared by every :class:`Acceptor` of a bridge."""

    def __init__(self, total: int, per_source: int):
        self.total = total
        self.per_source = per_source
        self._by_source: Counter[str] = Counter()
        self._count = 0
        self._lock = threading.Lock()

    def admit(self, host: str) -> str | None:
        """Take a place for a connection from ``host``; None when taken, else why not."""
        with self._lock:
            if self._count >= self.total:
                return "too_many_connections"
            if self._by_source[host] >= self.per_source:
                return "too_many_per_source"
            self._count += 1
            self._by_source[host] += 1
            return None

    def release(self, host: str) -> None:
        with self._lock:
            self._count -= 1
            self._by_source[host] -= 1
            if not self._by_source[host]:
                del self._by_source[host]

    @property
    def held(self) -> int:
        return self._count


class _Counted:
    """An accepted connection that gives its place back to the limits when it is closed."""

    def __init__(self, connection: StreamConnection, release: Callable[[], None]):
        self._connection = connection
        self._release: Callable[[], None] | None = release
        self._lock = threading.Lock()

    def send(self, data: bytes) -> None:
        self._connection.send(data)

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        return self._connection.receive(max_bytes, timeout)

    def close(self) -> None:
        try:
            self._connection.close()
        finally:
            with self._lock:
                release, self._release = self._release, None
            if release is not None:
                release()

    def __getattr__(self, name: str) -> Any:  # what else the transport's connection offers
        return getattr(self._connection, name)


RefusedHandler = Callable[["Acceptor", str, str], None]


class Acceptor:
    """Accepts connections on a listener until closed, and hands each to ``on_connection``.

    A connection from a source ``sources`` does not admit, or past ``limits``, is closed at once
    and reported to ``on_refused(acceptor, reason, detail)`` (``not_allowed``,
    ``too_many_connections``, ``too_many_per_source``). When accepting fails (out of file
    descriptors: EMFILE, ENFILE) the loop waits, from 0.1 s doubling to 1 s, and reports
    ``accept_failed``: a listener whose backlog cannot be taken never spins.
    """

    def __init__(self, listener: StreamListener, name: str,
                 on_connection: Callable[[StreamConnection, Address], None],
                 limits: ConnectionLimits | None = None, sources: Sources | None = None,
                 on_refused: RefusedHandler | None = None):
        self.listener = listener
        self.name = name
        self.on_connection = on_connection
        self.limits = limits
        self.sources = sources
        self.on_refused = on_refused
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"accept-{name}", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        failures = 0
        while not self.closed.is_set():
            try:
                got = self.listener.accept(POLL)
            except OSError as exc:
                if self.closed.is_set():
                    return
                failures += 1
                pause = min(ACCEPT_BACKOFF[0] * 2 ** (failures - 1), ACCEPT_BACKOFF[1])
                self._refused("accept_failed", f"{exc}; trying again in {pause:g} s")
                self.closed.wait(pause)
                continue
            failures = 0
            if got is not None:
                self._take(*got)

    def _take(self, connection: StreamConnection, peer: Address) -> None:
        host = peer[0]
        if self.sources is not None and not self.sources.admits(peer):
            connection.close()
            self._refused("not_allowed", f"a connection from {host} (taken from: "
                                            f"{self.sources})")
            return
        limits = self.limits
        if limits is not None:
            refused = limits.admit(host)
            if refused is not None:
                connection.close()
                self._refused(refused, f"closed a connection from {host} ({limits.held} held, "
                                       f"at most {limits.total}, {limits.per_source} per source)")
                return
            connection = _Counted(connection, lambda: limits.release(host))
        try:
            self.on_connection(connection, peer)
        except Exception:  # a bug, or no thread to be had: this connection only
            BUGS.bug("accept_handler", f"{self.name}: error while taking a connection from "
                                       f"{host}")
            connection.close()
            self._refused("handler_error", f"a connection from {host}")

    def _refused(self, reason: str, detail: str) -> None:
        if self.on_refused is not None:
            self.on_refused(self, reason, detail)
        else:
            _WARNER.warn(self.name, reason, detail)

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        self.listener.close()
        self._thread.join(timeout=2)


def deliver(link: DatagramLink | StreamLink, frame: bytes, source: Address) -> None:
    """Hand a frame to the link's handler. A handler that raises has a bug; it is counted, its
    traceback logged once per minute, and the link keeps receiving."""
    try:
        link.on_frame(frame, link, source)
    except Exception:
        BUGS.bug("handler_error", f"{link.name}: error while handling a frame from {source} "
                                  "(a bug: please report it)")
        link.on_lost(None, "handler_error")
