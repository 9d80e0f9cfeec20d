"""The queue and the threads of a link, both kinds: the :class:`~rosgate.scheduler.Scheduler`,
its lock, a send thread and a receive thread, closing (what never left is counted), what
waits."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from ..config import MAX_DELAY_DEFAULT, LinkConfig
from ..drops import Drop
from ..scheduler import Due, Scheduler
from .base import FrameHandler, LinkCounters, LostHandler


class _SendingBase:
    """What both kinds of link share beside each frame's way: the scheduler, its lock, the two
    threads, closing and what waits (the send turn is :class:`~.datagram._Sending`'s)."""

    on_frame: FrameHandler
    on_lost: LostHandler
    # each kind's own: closing its endpoint or connection, its two threads, and sending one
    # packet in this thread's turn (False: dropped, counted)
    _close_io: Callable[[], None]
    _receive_loop: Callable[[], None]
    _send_loop: Callable[[], None]
    _send_due: Callable[[Due], bool]
    #: told once the link has closed (a stream link's owner forgets it)
    on_close: Callable[[Any], None] | None = None
    #: told as soon as it starts closing, before its threads end (a client stops sending)
    on_closing: Callable[[Any], None] | None = None

    def _init_sending(self, name: str, budget: LinkConfig | None, overhead: int, packet: int,
                      frames: int, bytes_: int, one_line: bool = False) -> None:
        self.name = name
        self.closed = threading.Event()
        self.counters = LinkCounters()
        self.scheduler = Scheduler(
            bandwidth=budget.bandwidth if budget else None, overhead=overhead,
            max_delay=budget.max_delay if budget else MAX_DELAY_DEFAULT, frames=frames,
            bytes=bytes_, packet=packet, one_line=one_line)
        # entered as the plain lock on the way out (a Condition's own with-statement costs a
        # Python call each way, ~0.3 us); the send thread waits on the condition
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._busy = False  # a thread is sending (inline or the send thread): one at a time
        #: callers waiting for the turn (see DatagramLink._await_turn), told when it is free
        self._turn = threading.Condition(self._lock)
        self._turn_waiters = 0
        self._stuck = False  # the last wait for the turn timed out: the link is the bottleneck
        #: what a stream's inline write left unwritten: it goes before anything else
        self._rest: Due | None = None

    def _start(self) -> None:
        self._threads = [threading.Thread(target=loop, name=f"{kind}-{self.name}", daemon=True)
                         for kind, loop in (("rx", self._receive_loop), ("tx", self._send_loop))]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        with self._wake:  # once only, whichever thread gets here first
            if self.closed.is_set():
                return
            self.closed.set()
            self._wake.notify_all()
        if self.on_closing is not None:
            self.on_closing(self)
        self._close_io()
        for thread in self._threads:
            # an unstarted thread (the receive thread failed first) sees `closed` and returns
            if thread is not threading.current_thread() and thread.ident is not None:
                thread.join(timeout=2)
        with self._wake:  # what never reached the transport is a drop, and counted as one
            unsent = self.scheduler.clear()
            if self._rest is not None:
                unsent.append(self._rest.sender)
                self._rest = None
        for sender in unsent:
            sender.drop(Drop.LINK_DOWN, f"{self.name} closed with the frame still queued")
        if self.on_close is not None:
            self.on_close(self)

    def queue_depth(self, sender: Any) -> int:
        with self._lock:
            return self.scheduler.depth(sender)

    def queued(self) -> int:
        """Messages waiting (not started), all senders."""
        with self._lock:
            return self.scheduler.waiting

    def forget(self, sender: Any) -> None:
        with self._lock:
            self.scheduler.forget(sender)

    def _count_drops(self) -> None:
        """Count what the scheduler dropped (outside the lock: counting may log)."""
        dropped = self.scheduler.dropped
        while dropped:
            sender, reason, detail = dropped.pop(0)
            sender.drop(reason, f"{self.name}: {detail}")
