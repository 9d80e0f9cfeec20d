"""Packetizers: how a datagram link cuts a frame into packets and puts them back together.

A link's own packetizer cuts the frames of topics without one: ``fragments`` (built in) cuts
what is longer than ``max_frame``; on links of small frames (:data:`SMALL_FRAME`) ``compact``
cuts every frame. Loss recovery (``recovery: fec``, ``recovery: retransmit``) is packetizers
too: a topic picks one by name, with options from ``plugins: {NAME: {...}}`` and its own on top
(``recovery: {fec: {overhead: 0.25}}``).

A plugin subclasses :class:`Packetizer` (``name``, ``magic``, ``cut``, ``feed``, ``cost``) and
registers it through the ``rosgate_packetizers`` hook. Every packet starts with one of its
two-byte magics, so the receiving link finds its packetizer without a setting (``RG`` and ``RB``
are the link's own). A link makes one instance of each packetizer it meets, for every topic and
peer. Threads: :meth:`~Packetizer.cut` and :meth:`~Packetizer.sent` run on the thread whose turn
it is to send (the link's send thread, or the caller's while the link is idle: one at a time),
:meth:`~Packetizer.feed` on the receive thread, :meth:`~Packetizer.timer` after every feed and
every ``sent`` and otherwise on the receive thread — or, for one that implements ``sent``, on
the send thread: such a one locks what the threads touch, and calls its :class:`PacketLink`
outside that lock.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, Protocol

from .drops import Reason
from .transport import Address

#: what a reassembler's partial frame costs beyond its bytes (its objects, its entries in the
#: tables): measured with tracemalloc (core/tests/test_framing.py checks the accounting covers it)
PARTIAL_COST = 1024

#: a packet as :meth:`Packetizer.cut` may give it: bytes, or the parts of one packet (a header
#: and a view of the frame), which the link sends without joining them where the transport can
Packet = bytes | tuple[bytes | memoryview, ...]

#: magics a packetizer may not claim: the link's own whole frames (``RG``) and batches (``RB``)
RESERVED_MAGIC = (b"RG", b"RB")
#: below this ``max_frame`` (CAN's 8, CAN FD's 64) a link cannot spare 14 bytes of fragment
#: header: its own packetizer is :data:`SMALL_FRAME_PACKETIZER`, whatever the transport
SMALL_FRAME = 256
SMALL_FRAME_PACKETIZER = "compact"


def own_packetizer(max_frame: int) -> str:
    """The name of the own packetizer of a datagram link of ``max_frame``-byte packets."""
    return SMALL_FRAME_PACKETIZER if max_frame < SMALL_FRAME else "fragments"


class PacketLink(Protocol):
    """What a packetizer may ask of the link that made it."""

    name: str
    #: the largest packet the transport carries
    max_frame: int
    #: the largest frame a packetizer may put together
    max_message: int

    def lost(self, topic_id: int | None, reason: Reason) -> None:
        """Count a frame given up (``fragment_lost``, ``reassembly_overflow``...) against its
        topic (None: unknown). Once per frame."""

    def recovered(self, topic_id: int) -> None:
        """A frame that arrived whole only thanks to the recovery (repair, retransmission)."""

    def answer(self, packet: bytes, to: Address) -> None:
        """Send a small packet now, outside the queue (an acknowledgement), counted against the
        budget of ``to``. One that cannot be sent is not retried."""

    def repeat(self, sender: Any, to: Address, packets: list[bytes]) -> None:
        """Queue ``packets`` again for ``sender`` (what :meth:`Packetizer.cut` was given),
        before its other packets."""


class Packetizer(ABC):
    """Base class of packetizer plugins (see the module's docstring)."""

    #: the name users write in bringup.yaml (``recovery: fec``)
    name: ClassVar[str]
    #: the first two bytes of every packet it makes; unique among installed packetizers
    magic: ClassVar[tuple[bytes, ...]]
    #: True: as a link's own packetizer it gets every frame and every datagram (so its packets
    #: need no magic); a packet it cuts may hold several datagrams (``max_frame`` bytes each but
    #: the last), sent back to back: pieces without a frame id never interleave
    cuts_every_frame: ClassVar[bool] = False
    #: seconds after a frame left within which it may still arrive, sent again (a selective
    #: repeat's deadline); None: what is lost stays lost. A receiver of a reliable topic holds
    #: the frames after a gap this long for the missing one, to publish them in order
    resends_within: ClassVar[float | None] = None

    def __init__(self, link: PacketLink):
        self.link = link

    @abstractmethod
    def cut(self, frame: bytes, sender: Any, to: Address, options: Any) -> list[Packet]:
        """The packets of ``frame`` for ``to``, each at most ``link.max_frame`` bytes; put
        ``sender.topic_id`` in them, so a frame lost on the way is counted against its topic.
        ``options``: the topic's ``Options``. Raise :class:`rosgate.FramingError`
        for a frame it cannot cut (counted ``send_error``)."""

    def sent(self, packet: bytes, to: Address, now: float) -> None:
        """The last packet of a frame it cut has left the link (``now``: time.monotonic()), e.g.
        to start a retransmission timer. Not implemented (the default): the link does not call
        it, nor :meth:`timer` from its send thread."""
        return None

    @abstractmethod
    def feed(self, packet: bytes | memoryview, source: Address, now: float) -> bytes | None:
        """Take one packet from the network (a view valid during the call: copy what you keep);
        the frame when it completes one. Raise :class:`rosgate.FramingError` for a
        malformed one (counted ``bad_fragment``); keep what you hold bounded in time and memory,
        counting every frame given up with ``link.lost``."""

    def timer(self, now: float) -> float | None:
        """Do what is due at ``now`` (ask again for what is missing, give up what is late); when
        to be called next (None: when the link is idle, at least every 0.2 s). Also called after
        every packet fed (and, with :meth:`sent`, every frame sent)."""
        return None

    def moved(self, old: Address, new: Address) -> None:
        """The far side at ``old`` is at ``new`` from now on (it roamed, a NAT rebound it):
        what is kept for ``old`` (frames not yet acknowledged) goes to ``new``. Called from
        the link's receiving thread; the send thread's timers run right after. By default
        nothing is kept per address."""
        return None

    def resumed(self, down: float, now: float) -> None:
        """The link's line was gone for ``down`` seconds and is back (``now``: time.monotonic());
        meanwhile nothing left or came and :meth:`timer` was not called. Push the clocks of what
        you keep on by ``down`` (and ask again, or probe, at once), so that nothing is given up
        for the outage itself. Called from the transport's thread that saw the line return,
        before the link's timers run again. By default nothing is kept by time."""
        return None

    @classmethod
    @abstractmethod
    def cost(cls, frame: int, max_frame: int, options: Any) -> tuple[int, int]:
        """(bytes, packets) that one frame of ``frame`` bytes takes on a link of ``max_frame``,
        without the transport's own per-packet headers, for ``rosgate check``'s budget."""
