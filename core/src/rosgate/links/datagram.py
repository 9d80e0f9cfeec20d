"""A datagram link's every frame, out and in: sent from the caller's thread when nothing waits
(whole, batched, or cut by a packetizer), queued otherwise; each datagram in dispatched to the
packetizer of its magic, batches split, whole frames handed to the router; a packetizer's
answers (acknowledgements) sent at once, and its timer armed on the send thread. Every receive
counts what a peer's bytes cause and never dies of input; an unexpected error's traceback is
logged once per reason per minute (:data:`rosgate.warn.BUGS`)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any, cast

from ..drops import Drop
from ..packetizer import Packet, Packetizer
from ..scheduler import Due, Outgoing
from ..transport import Address
from ..warn import BUGS
from ..wire import framing
from .base import POLL, Link, Sender
from .datagram_base import INLINE_MAX, DatagramBase, batch, batch_size
from .sending import _SendingBase


class _Sending(_SendingBase):
    """The send turn both kinds of link share (a frame sent from the caller's thread when
    nothing waits), what they queue, and each frame handed to the handler."""

    def _deliver(self, frame: bytes, source: Address) -> None:
        """Hand a frame to the handler; one that raises has a bug: counted, and the link goes on."""
        try:
            self.on_frame(frame, self, source)  # type: ignore[arg-type]  # a Link subclass's
        except Exception:
            BUGS.bug("handler_error", f"{self.name}: error while handling a frame from {source} "
                                      "(a bug: please report it)")
            self.on_lost(None, Drop.HANDLER_ERROR)

    def _claim(self, to: Any, size: int) -> bool:
        """Under the lock: whether the calling thread may send ``size`` bytes to ``to`` itself
        now (nothing sending or queued, the budget's tokens taken); then it is its turn until
        :meth:`_release`."""
        if (self.closed.is_set() or self._busy or self._rest is not None
                or not self.scheduler.may_send_now(to, size)):
            return False
        self._busy = True
        self._stuck = False
        return True

    def _release(self) -> None:
        """The caller's turn is over: the send thread takes what waits."""
        with self._lock:
            self._busy = False
            if not self.scheduler.idle or self._rest is not None:
                self._wake.notify()
            if self._turn_waiters:
                self._turn.notify_all()

    def _send_now(self, packet: bytes, sender: Any, to: Any) -> bool | None:
        """A whole frame sent from the caller's thread if it may leave at once (a quiet link:
        no message object, no hand-off): whether it went; None: queue it."""
        with self._lock:
            if not self._claim(to, len(packet)):
                return None
        try:
            sent = self._send_due(Due(packet, to, sender, SENT_INLINE))
            self.counters.inline_out += sent
            return sent
        finally:
            self._release()

    def _put(self, message: Outgoing) -> bool:
        """Queue ``message`` for the send thread. False when it was dropped (counted)."""
        with self._lock:
            queued = not self.closed.is_set() and self.scheduler.put(message)
            if queued and not self._busy:
                self._wake.notify()
        if self.scheduler.dropped:
            self._count_drops()
        if not queued and self.closed.is_set():
            message.sender.drop(Drop.LINK_DOWN, f"{self.name} is closed")
        return queued


class _Gather:
    """A packet as its parts (a header, a view of the frame) for scatter-gather sending, no copy
    of the frame; the scheduler takes it for a packet of ``len()`` bytes."""

    __slots__ = ("parts", "size")

    def __init__(self, parts: tuple[bytes | memoryview, ...]):
        self.parts = list(parts)
        self.size = sum(map(len, parts))

    def __len__(self) -> int:
        return self.size


#: what a Due sent from the caller's thread ends: its one frame (see _Sending._send_now)
SENT_INLINE = Outgoing(None, None, 0, list)
#: bytes a batch of a topic with recovery leaves its packetizer for its header, so the batch
#: and the header fit one packet (retransmit's takes 14, fec's 21)
REPAIR_HEADROOM = 64


def _groups(frames: list[bytes], limit: int) -> Iterator[tuple[list[bytes], int]]:
    """Consecutive frames in groups whose batch fits ``limit`` bytes (a frame alone when it
    does not), with their bytes in all."""
    start = 0
    while start < len(frames):
        total, end = 0, start
        while end < len(frames) and batch_size(total + len(frames[end]), end - start + 1) <= limit:
            total += len(frames[end])
            end += 1
        if end == start:  # a frame alone: sent as one
            total, end = len(frames[start]), start + 1
        yield frames[start:end], total
        start = end


class DatagramLink(DatagramBase, _Sending, Link):
    """A bound datagram endpoint. Frames out: whole when they fit ``max_frame`` (batched with
    others for one destination), else cut by the link's own packetizer, or by the topic's
    ``recovery``; a bare link's whole, never batched. Datagrams in: from ``sources`` only, to the
    packetizer of their magic (``packetizers``: the installed ones by default); a bare link's as
    they came. An own packetizer that ``cuts_every_frame`` (small frames) takes every frame and
    every datagram. It is the :class:`~rosgate.packetizer.PacketLink` of its packetizers (one of
    each, made on first use); the timers of those that implement ``sent`` run on its send
    thread, the others' on its receive thread. An endpoint that says when its line is gone
    (``watch_line``: a serial device unplugged) stops it sending until the line is back:
    reliable frames wait (at most ``hold_frames`` and ``hold_bytes``, the oldest dropped first:
    ``queue_full``), best-effort ones are dropped (``link_down``), and the packetizers' clocks
    stand still (:meth:`~rosgate.packetizer.Packetizer.resumed`)."""

    datagram = True

    #: a packet sent as its parts (the send thread, DatagramBase, tells it by its type)
    _parts = _Gather

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        assert to is not None, "a datagram link needs a destination"
        size = len(frame)
        if self.bare and size > self.max_frame:
            sender.drop(Drop.TOO_LARGE_FOR_BARE_FRAMING,
                        f"{size} bytes, {self.name} carries at most {self.max_frame}")
            return False
        delivery = sender.delivery
        up = self.line_up
        if not (up or delivery.reliable):  # it would be stale by the time the line is back
            sender.drop(Drop.LINK_DOWN, f"{self.name}: its line is gone")
            return False
        whole = self.bare or delivery.whole
        plain = delivery.packetizer is None and not self.cuts  # whole or fragments
        one = whole or plain and size <= self.max_frame
        # a frame a topic's recovery cuts (one packet or several) leaves from here too
        cut_here = not self.cuts and size <= INLINE_MAX
        inline = self._send_now if one else self._send_fragments_now if cut_here else None
        if inline is not None and up:
            sent = inline(frame, sender, to)
            if sent is None and self._await_turn() and self._send_waiting():
                sent = inline(frame, sender, to)  # what waited is gone: the link is idle
            if sent is not None:
                return sent
        queued = self._put(Outgoing(sender, to, size,
                                    lambda: self._cut(frame, sender, to, whole),
                                    time.monotonic(), batchable=one and not whole))
        if not up:
            self._held()
        return queued

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Frames of one sender: on an idle link those that fit share datagrams sent from here;
        else each is queued (and coalesced again by the send thread)."""
        assert to is not None, "a datagram link needs a destination"
        delivery = sender.delivery
        if len(frames) == 1:  # (most calls: one message taken)
            return int(self.send(frames[0], sender, to))
        if not frames or self.bare or self.cuts or delivery.whole or not self.line_up:
            return sum(self.send(frame, sender, to) for frame in frames)
        if delivery.packetizer is not None:
            return self._send_repaired(frames, sender, to)
        sent = 0
        for group, total in _groups(frames, self.max_frame):
            go = len(group) > 1
            if go:
                with self._lock:
                    go = self._claim(to, batch_size(total, len(group)))
            if not go:
                sent += sum(self.send(frame, sender, to) for frame in group)
                continue
            try:
                batched = self._send_batch([Due(frame, to, sender) for frame in group], to)
                self.counters.inline_out += batched
                sent += batched
            finally:
                self._release()
        return sent

    def _send_repaired(self, frames: list[bytes], sender: Sender, to: Address) -> int:
        """Frames of a topic with recovery: those that fit one packet together go to its
        packetizer as one batch (one packet to repair and acknowledge, not one per message)."""
        sent = 0
        for group, _ in _groups(frames, self.max_frame - REPAIR_HEADROOM):
            if len(group) == 1:
                sent += self.send(group[0], sender, to)
            elif self.send(b"".join(batch(group)), sender, to):
                sent += len(group)
                with self._lock:  # the link's counters count its messages, as for any batch
                    self.counters.frames_out += len(group) - 1
                    self.counters.coalesced_out += len(group)
        return sent

    def _cut(self, frame: bytes, sender: Sender, to: Address, whole: bool) -> list[bytes]:
        """A frame's packets, made when it starts (counters and FEC coding on the send thread)."""
        delivery = sender.delivery
        own = self.cuts or delivery.packetizer is None
        if whole or own and not self.cuts and len(frame) <= self.max_frame:
            return [frame]
        packetizer = self.own if own or delivery.packetizer is None \
            else self._by_name.get(delivery.packetizer.name) or self._make(delivery.packetizer)
        packets = packetizer.cut(frame, sender, to, delivery.packetizer_options)
        return [packet if type(packet) is bytes else self._packet(packet) for packet in packets]

    def _packet(self, packet: Packet) -> bytes:
        if not isinstance(packet, tuple):
            return packet
        # a _Gather stands for its packet: the scheduler only takes its len()
        return cast(bytes, _Gather(packet)) if self._gather else b"".join(packet)

    def _send_fragments_now(self, frame: bytes, sender: Any, to: Address) -> bool | None:
        """A frame longer than ``max_frame``, or one a topic's recovery cuts, cut and sent from
        the caller's thread as :meth:`_send_now` sends a whole one: a hand-off to the send thread
        may take milliseconds on a busy interpreter, long enough for a latest-only frame to be
        superseded, and costs a wake-up per message. The rest goes to the send thread once
        anything else waits or the budget runs short."""
        with self._lock:
            if not self._claim(to, self.max_frame):  # the first fragment's tokens
                return None
        scheduler, lock, counters = self.scheduler, self._lock, self.counters
        try:
            packets = self._cut(frame, sender, to, False)
            # all the packets in one call when the endpoint can and no budget limits; else one at
            # a time, each after a look at what else waits
            turn = len(packets) if scheduler.rate is None and self._send_datagrams else 1
            for start in range(0, len(packets), turn):
                if start:
                    with lock:  # anything else waiting, or a budget short: the send thread's
                        if not scheduler.may_send_now(to, len(packets[start])):
                            rest, now = packets[start:], time.monotonic()
                            scheduler.resume(Outgoing(sender, to, sum(map(len, rest)), list, now),
                                             rest, now)
                            return True
                end = start + turn
                if not self._send_run(packets[start:end], sender, to, end >= len(packets)):
                    return False
            counters.inline_out += 1
            self._ended(packets[-1], to)
            return True
        finally:
            self._release()

    def _send_run(self, packets: list[bytes], sender: Any, to: Address, last: bool) -> bool:
        """Packets of one frame in a row, in one call where the endpoint can; ``last``: they end
        the frame. False when they could not be sent (counted)."""
        try:
            if len(packets) > 1 and self._send_datagrams is not None:
                self._send_datagrams([cast(_Gather, p).parts if type(p) is _Gather else [p]
                                      for p in packets], to)
            else:
                for packet in packets:
                    if type(packet) is _Gather:
                        self._send_parts(cast(_Gather, packet).parts, to)
                    else:
                        self.endpoint.send(packet, to)
        except OSError as exc:
            if self._repairs(packets[0]) and not self.closed.is_set():
                return True  # lost on the way, as far as its packetizer goes: it sends it again
            sender.drop(Drop.LINK_DOWN if self.closed.is_set() else Drop.SEND_ERROR,
                        f"to {to} on {self.name}: {exc}")
            return False
        counters = self.counters
        counters.packets_out += len(packets)
        counters.frames_out += last
        for packet in packets:
            counters.bytes_out += len(packet)
            sender.on_wire(len(packet), False)
        return True

    def _send_due(self, due: Due) -> bool:
        packet, to, sender = due.packet, due.to, due.sender
        count = 1
        try:
            if type(packet) is _Gather:
                self._send_parts(cast(_Gather, packet).parts, to)
            elif self.cuts and not sender.delivery.whole:  # a packet of several datagrams
                pieces = range(0, len(packet), self.max_frame)
                count = len(pieces)
                for i in pieces:
                    self.endpoint.send(packet[i:i + self.max_frame], to)
            else:
                self.endpoint.send(packet, to)
        except OSError as exc:
            if self._repairs(packet) and not self.closed.is_set():
                # no route for now (a host between two addresses): lost on the way, as far as
                # its packetizer goes, which sends it again (the receiver counts what never came)
                self._left(due, packet, to)
                return False
            # a message cut short by close() was counted there, unless this was its last packet
            if due.ends is not None or not self.closed.is_set():
                sender.drop(Drop.SEND_ERROR, f"to {to} on {self.name}: {exc}")
            return False
        counters = self.counters
        counters.packets_out += count
        counters.bytes_out += len(packet)
        if due.ends is not None:
            counters.frames_out += 1
        sender.on_wire(len(packet), due.again)
        self._left(due, packet, to)
        return True

    def _left(self, due: Due, packet: Any, to: Address) -> None:
        """The last packet of a frame has left (or was lost leaving): its packetizer's timer."""
        if due.ends is not None and due.ends is not SENT_INLINE:
            self._ended(packet, to)

    def _ended(self, packet: Any, to: Address) -> None:
        """``packet``, the last of a frame, has left: a packetizer that implements ``sent`` is
        told, and the send thread runs its timer when it asks."""
        if type(packet) is bytes:
            packetizer = self._by_magic.get(packet[:2])
            if packetizer in self._sending:
                now = time.monotonic()
                packetizer.sent(packet, to, now)
                self._arm(packetizer.timer(now))

    def answer(self, packet: bytes, to: Address) -> None:
        """Sent at once (counted against the budget); one that fails is asked for again anyway.
        Never to a source read on probation (a stranger, or a client that moved before a genuine
        frame of it moved its address): a replayed datagram must not make this side talk."""
        if self.sources is not None and not self.sources.vouches_for(to):
            return
        with self._lock:
            self.scheduler.charge(to, len(packet))
        try:
            self.endpoint.send(packet, to)
        except OSError:
            pass

    def _arm(self, due: float | None) -> None:
        """The send thread runs the timers of the packetizers that implement ``sent`` at
        ``due`` at the latest: woken when that is sooner than the time it waits for. (Read
        first without the lock: a time already set as soon or sooner is run by the send thread,
        which sets the next under the lock, after what every ``sent`` before said.)"""
        if due is None:
            return
        armed = self._tx_timer
        if armed is not None and armed <= due:
            return
        with self._wake:
            if self._tx_timer is None or due < self._tx_timer:
                self._tx_timer = due
                self._wake.notify()

    def _receive_loop(self) -> None:
        receive_into = getattr(self.endpoint, "receive_into", None)
        if receive_into is None:
            receive: Callable[[float], tuple[bytes | memoryview, Address] | None] = \
                self.endpoint.receive
        else:
            # one buffer for every datagram, so long that one that fills it is too long
            buffer = memoryview(bytearray(max(self.max_frame, 65_535) + 1))
            endpoint: Any = self.endpoint
            overflowed = [getattr(endpoint, "overflowed", None)]  # (counted so far)

            def receive(timeout: float) -> tuple[bytes | memoryview, Address] | None:
                got = receive_into(buffer, timeout)
                if got is None:
                    return None
                size, source, self.arrived = got
                if overflowed[0] is not None and endpoint.overflowed != overflowed[0]:
                    # the kernel dropped datagrams: the receive buffer was full
                    for _ in range((endpoint.overflowed - overflowed[0]) % 2**32):
                        self.on_lost(None, Drop.RECEIVE_BUFFER_FULL)
                    overflowed[0] = endpoint.overflowed
                if size >= len(buffer):
                    self.on_lost(None, Drop.OVERSIZED_DATAGRAM)
                    return None
                return buffer[:size], source

        closed = self.closed
        timer: float | None = None  # when the packetizers' timers run next on this thread
        while not closed.is_set():
            timeout = POLL if timer is None else min(POLL, max(0.001, timer - time.monotonic()))
            try:
                got = receive(timeout)
            except OSError:  # passing, or the endpoint closed: the loop's test tells
                continue
            except Exception:  # a transport plugin's bug must not silently end the link
                BUGS.bug("transport_error", f"{self.name}: the transport's receive failed "
                                            "(a bug in the plugin)")
                self.on_lost(None, Drop.TRANSPORT_ERROR)
                closed.wait(POLL)  # do not spin on a receive that fails at once
                continue
            now = time.monotonic()
            if got is None or timer is not None and now >= timer:
                timer = self._run_timers(now)
            if got is None:  # idle: the send thread's timers too (a timer that said None)
                self._arm(self._run_timers(now, sending=True))
                continue
            fed = self._datagram(*got, now)
            if fed is not None:  # what it was given may have moved its timer
                due = fed.timer(now)
                if fed in self._sending:  # its timer runs on the send thread
                    self._arm(due)
                elif due is not None and (timer is None or due < timer):
                    timer = due

    def _datagram(self, datagram: bytes | memoryview, source: Address,
                  now: float) -> Packetizer | None:
        """One datagram (a view of the receive buffer); the packetizer it was fed to, if any."""
        if self.sources is not None and not self.sources.admits(source, datagram):
            self.on_lost(None, Drop.NOT_ALLOWED)
            return None
        counters = self.counters
        counters.packets_in += 1
        counters.bytes_in += len(datagram)
        kind = datagram[1] if len(datagram) > 1 and datagram[0] == 0x52 else 0  # "R?"
        if self.bare or kind == 0x47 and not self.cuts:  # "RG": an envelope, the most common
            packetizer = None
        elif self.cuts:  # every datagram is its own packetizer's
            packetizer = self.own
        elif kind == 0x42:  # "RB": a batch
            self._unbatch(datagram, source)
            return None
        else:
            magic = bytes(datagram[:2])
            packetizer = self._by_magic.get(magic, _UNKNOWN)
            if packetizer is _UNKNOWN:
                packetizer = self._receiver(magic)
        if packetizer is None:  # a whole frame
            counters.frames_in += 1
            self._deliver(datagram if type(datagram) is bytes else bytes(datagram), source)
            return None
        try:
            frame = packetizer.feed(datagram, source, now)
        except framing.FramingError:
            self.on_lost(None, Drop.BAD_FRAGMENT)
            return packetizer
        except Exception:  # a packetizer must raise FramingError; anything else is its bug
            BUGS.bug("packetizer_error", f"{self.name}: packetizer {packetizer.name} failed on a "
                                         "packet (a bug in the plugin)")
            self.on_lost(None, Drop.BAD_FRAGMENT)
            return packetizer
        if frame is None:
            return packetizer
        if frame[:2] == framing.BATCH_MAGIC:  # a topic's batch, repaired as one (_send_repaired)
            self._unbatch(frame, source)
        else:
            counters.frames_in += 1
            self._deliver(frame, source)  # the handler's to keep (rclpy takes it uncopied)
        return packetizer

    def _unbatch(self, datagram: bytes | memoryview, source: Address) -> None:
        """A batch's frames to the handler, read inline (no generator: a cost per message)."""
        counters = self.counters
        end, offset, deliver = len(datagram), _BATCH_START, self._deliver
        while offset < end:
            start = offset + _LENGTH_SIZE
            if start > end or (offset := start + _length(datagram, offset)[0]) > end:
                self.on_lost(None, Drop.BAD_BATCH)
                break
            counters.frames_in += 1
            counters.coalesced_in += 1
            deliver(bytes(datagram[start:offset]), source)

    def _close_io(self) -> None:
        self.endpoint.close()


# reading a batch (see batch)
_BATCH_START, _LENGTH_SIZE, _length = (len(framing.BATCH_MAGIC), framing.LENGTH.size,
                                       framing.LENGTH.unpack_from)

#: a magic the link has not looked up yet
_UNKNOWN: Any = object()
