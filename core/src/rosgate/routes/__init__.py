"""Routes: one topic, service or action on one side of a link. A message's whole data path
(transmit, receive, the envelope's framing) is :mod:`.route`'s; a reliable topic's order comes
from :mod:`rosgate.inorder`. Beside the path: what a route counts (:mod:`.counters`), what it
says of its entry (:mod:`.said`), what waits (:mod:`.held`), ``framing: none`` (:mod:`.bare`)."""

from ..warn import Warner
from .bare import BareFraming, BarePort
from .counters import QUIET_REASONS, Counters, SideSender
from .held import BATCH_BYTES, BATCH_FRAMES, max_wait_ns
from .route import (
    DRAIN_BYTES,
    DRAIN_FRAMES,
    SEAL_IN_PLACE,
    EnvelopeFraming,
    ReceiveRoute,
    Route,
    TransmitRoute,
)

__all__ = ["BATCH_BYTES", "BATCH_FRAMES", "DRAIN_BYTES", "DRAIN_FRAMES", "QUIET_REASONS",
           "SEAL_IN_PLACE", "BareFraming", "BarePort", "Counters", "EnvelopeFraming",
           "ReceiveRoute", "Route", "SideSender", "TransmitRoute", "Warner", "max_wait_ns"]
