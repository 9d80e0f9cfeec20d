"""The conformance suite of service framings (:mod:`rosgate.service_framing`)::

    from rosgate_testing import ServiceFramingConformance

    class TestSerialDatagramConformance(ServiceFramingConformance):
        service_framing = SerialDatagramCalls
        codec = MsgpackCodec                   # a codec the framing's entries may use

It checks the serving side (``direction: receive``), with a real serving route of
``std_srvs/srv/Trigger`` (no ROS server behind it) on a port, over connected stream sockets: the
class is found through its entry point; the port carries the name it was given; ``accepted``
returns at once; seeded garbage, each piece on a connection of its own, is counted as a drop
(by the port or by the route) and the connection is closed, never answered; a connection that
says nothing is closed after ``idle_timeout`` and counted. The calling side needs a device to
call: test it end to end, against the device's own encoder.
"""

from __future__ import annotations

import random
import socket
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import pytest

from rosgate import Codec, Direction, ServerRoute, ServiceConfig, ServiceFraming, SocketConnection
from rosgate.builtin import NoCipher
from rosgate.keyring import StaticKeys
from rosgate.options import parse
from rosgate.service_framing import CallPort
from rosgate.services import Deadlines, ServiceCodec
from rosgate.warn import Warner

from .helpers import assert_registered

PEER = ("127.0.0.1", 40000)
TIMEOUT = 1.0       # the serving route's timeout: a request must arrive within it
IDLE_TIMEOUT = 0.3  # the port's: a connection may be silent this long
CLOSED_WITHIN = 5.0


class NoRosServer:
    """The serving route's ROS client, with no server behind it: a call is answered as a
    failure (``no_server``)."""

    def service_is_ready(self) -> bool:
        return False


class ServiceFramingConformance:
    """Subclass it as ``Test...`` and set :attr:`service_framing` and :attr:`codec`."""

    service_framing: ClassVar[type[ServiceFraming]]
    codec: ClassVar[type[Codec]]
    codec_options: ClassVar[Mapping[str, Any]] = {}
    garbage_connections: ClassVar[int] = 40

    @pytest.fixture
    def port(self):
        """(the port, its serving route, what it counted against no service)."""
        from std_srvs.srv import Trigger

        deadlines = Deadlines()
        entry = ServiceConfig(service="/kit/trigger", type="std_srvs/srv/Trigger",
                              direction=Direction.RECEIVE, remote="trigger", timeout=TIMEOUT,
                              max_request=4096)
        codec = ServiceCodec(self.codec, Trigger, parse(self.codec, self.codec_options))
        keys = StaticKeys(NoCipher(parse(NoCipher, {}), Path()))
        route = ServerRoute(entry, 0, codec, keys, Warner(), "/kit/trigger", Trigger, deadlines)
        route.entity = NoRosServer()
        port_drops: list[str] = []
        port = self.service_framing.server("kit:1", lambda _, reason, detail:
                                           port_drops.append(reason), IDLE_TIMEOUT)
        port.add(route)
        yield port, route, port_drops
        deadlines.close()

    def call(self, port: CallPort, data: bytes) -> tuple[socket.socket, float]:
        """A connection handed to the port; the far end, and how long ``accepted`` took."""
        near, far = socket.socketpair()
        far.settimeout(CLOSED_WITHIN)
        start = time.monotonic()
        port.accepted(SocketConnection(near), PEER)
        took = time.monotonic() - start
        if data:
            far.sendall(data)
        return far, took

    @staticmethod
    def answer_until_closed(far: socket.socket) -> bytes:
        """What the port wrote before it closed the connection (fails if it stays open)."""
        data = b""
        while chunk := far.recv(4096):  # socket.timeout: the port kept it open
            data += chunk
        far.close()
        return data

    @staticmethod
    def drops(route: ServerRoute, port_drops: list[str]) -> int:
        return len(port_drops) + sum(route.counters.drops.values())

    def test_found_through_its_entry_point(self) -> None:
        assert_registered("service_framing", self.service_framing)

    def test_the_port_has_the_name_it_was_given(self, port) -> None:
        assert port[0].name == "kit:1"

    def test_accepted_returns_at_once(self, port) -> None:
        far, took = self.call(port[0], b"")
        assert took < 0.5
        far.close()

    def test_garbage_is_counted_and_closed_without_an_answer(self, port) -> None:
        port, route, port_drops = port
        rng = random.Random(19)
        for index in range(self.garbage_connections):
            garbage = rng.randbytes(rng.choice((1, 3, 17, 200, 3000)))
            before = self.drops(route, port_drops)
            far, _ = self.call(port, garbage)
            far.shutdown(socket.SHUT_WR)
            assert self.answer_until_closed(far) == b"", f"garbage #{index} was answered"
            assert self.drops(route, port_drops) > before, f"garbage #{index} was not counted"
        assert route.counters.received == 0 and route.counters.sent == 0

    def test_a_silent_connection_is_closed_after_the_idle_timeout(self, port) -> None:
        port, route, port_drops = port
        far, _ = self.call(port, b"")
        start = time.monotonic()
        assert self.answer_until_closed(far) == b""
        assert IDLE_TIMEOUT <= time.monotonic() - start < TIMEOUT + 1
        assert self.drops(route, port_drops) == 1
