"""The ``can`` transport through the plugin kit's datagram suite, on python-can's ``virtual``
interface: classic CAN (8-byte frames) and CAN FD (64-byte frames), so the link's compact
pieces (rosgate-compact) carry every frame.

What a bus changes, declared to the suite: each end is a transport of its own on one channel
(a node does not hear its own frames); a receive reports ``(channel, receiving port)``, so an
answer goes to the sender's known port; order is kept, and checked; port 0 only sends, so the
addresses start at port 1; CAN FD pads a frame to the next length its DLC can say."""

from __future__ import annotations

import itertools
import uuid

import pytest
from can.util import dlc2len, len2dlc
from rosgate_testing import TransportConformance
from rosgate_transport_can import CanTransport


class TestCanConformance(TransportConformance):
    transport = CanTransport
    options = {"interface": "virtual"}
    answerable_source = False
    ordered = True

    @pytest.fixture
    def channel(self) -> str:
        # a virtual channel of its own: a bus left by another test must not hear this one
        return f"can-conformance-{uuid.uuid4().hex}"

    @pytest.fixture
    def plugin(self, channel: str) -> CanTransport:
        return CanTransport({**self.options, "channel": channel})

    @pytest.fixture
    def far_plugin(self, channel: str) -> CanTransport:
        return CanTransport({**self.options, "channel": channel})  # a second node on the bus

    @pytest.fixture
    def address(self):
        ports = itertools.count(1)
        return lambda: ("can0", next(ports))


class TestCanFdConformance(TestCanConformance):
    options = {"interface": "virtual", "fd": True}
    # a CAN FD frame has 0-8, 12, 16, 20, 24, 32, 48 or 64 data bytes: the plugin pads with
    # zeros, and the compact pieces carry the length that strips them again
    padded_length = staticmethod(lambda n: dlc2len(len2dlc(n)))
