"""How a udp receive waits: in the kernel's own recvmsg under the socket's SO_RCVTIMEO (one
system call per datagram, the option set only when the wait asked for changes), in poll where
the option cannot be set; a receive waiting when the endpoint closes ends at once."""

from __future__ import annotations

import os
import socket
import struct
import threading
import time

import pytest
from rosgate_transport_udp import UdpEndpoint, UdpTransport

TIMEVAL = struct.Struct("@ll")


@pytest.fixture
def pair():
    transport = UdpTransport({})
    a, b = transport.bind(("127.0.0.1", 0)), transport.bind(("127.0.0.1", 0))
    yield a, b
    a.close()
    b.close()


class Counting:
    """A socket (or poll object) stand-in that counts calls by name, and can refuse to set
    options as a system without SO_RCVTIMEO does."""

    def __init__(self, inner, refuse_options: bool = False):
        self.inner = inner
        self.calls: dict[str, int] = {}
        self.refuse = refuse_options

    def __getattr__(self, name):
        found = getattr(self.inner, name)
        if not callable(found):
            return found

        def counted(*args, **kwargs):
            self.calls[name] = self.calls.get(name, 0) + 1
            if self.refuse and name == "setsockopt":
                raise OSError(92, "Protocol not available")
            return found(*args, **kwargs)

        return counted


def rcvtimeo(endpoint: UdpEndpoint) -> float:
    seconds, micros = TIMEVAL.unpack(endpoint.sock.getsockopt(
        socket.SOL_SOCKET, socket.SO_RCVTIMEO, TIMEVAL.size))
    return seconds + micros / 1e6


def test_each_datagram_is_one_recvmsg_and_no_poll(pair):
    a, b = pair
    to = b.sock.getsockname()
    b.sock = sock = Counting(b.sock)
    b._readable = polls = Counting(b._readable)
    sent = [os.urandom(n) for n in (1, 100, 1_472, 10_000, 65_000)] * 10
    buffer = memoryview(bytearray(65_537))
    got = []
    for datagram in sent:
        a.send(datagram, to)
        one = b.receive_into(buffer, 2.0)
        assert one is not None, f"{len(got)} of {len(sent)} arrived"
        size, source, arrived = one
        assert source == a.sock.getsockname()
        assert abs(arrived - time.time_ns()) < 5e9  # the kernel's stamp: now, give or take
        got.append(bytes(buffer[:size]))
    assert got == sent
    assert sock.calls == {"recvmsg_into": len(sent), "setsockopt": 1}  # set once: one timeout
    assert polls.calls == {}
    assert 2.0 <= rcvtimeo(b) <= 2.011


def test_a_receive_with_nothing_to_take_waits_its_timeout_and_a_new_timeout_is_set(pair):
    _, b = pair
    b._readable = polls = Counting(b._readable)
    buffer = memoryview(bytearray(65_537))
    for timeout in (0.05, 0.3, 0.1):
        start = time.monotonic()
        assert b.receive_into(buffer, timeout) is None
        waited = time.monotonic() - start
        assert timeout * 0.9 <= waited < timeout + 1.0
        # the kernel counts it in its ticks (HZ 100 to 1000): up to 10 ms more
        assert timeout <= rcvtimeo(b) <= timeout + 0.011
    assert polls.calls == {}
    # a shorter wait (a packetizer's timer) waits in poll, which keeps to it, and leaves the
    # socket's timeout as it was; zero does not wait
    for timeout, most in ((0.0, 0.5), (0.01, 0.5)):
        start = time.monotonic()
        assert b.receive_into(buffer, timeout) is None
        waited = time.monotonic() - start
        assert timeout * 0.9 <= waited < most
    assert polls.calls == {"poll": 2}
    assert 0.1 <= rcvtimeo(b) <= 0.111


def test_closing_the_endpoint_ends_a_receive_waiting_in_the_kernel(pair):
    _, b = pair
    results: list = []
    waiting = threading.Thread(
        target=lambda: results.append(b.receive_into(memoryview(bytearray(65_537)), 30.0)))
    waiting.start()
    time.sleep(0.1)  # let it reach recvmsg (ending sooner is as good: it must end either way)
    start = time.monotonic()
    b.close()
    waiting.join(5.0)
    assert not waiting.is_alive(), "a receive kept waiting after close"
    assert time.monotonic() - start < 5.0
    assert results == [None]


def test_where_the_timeout_cannot_be_set_a_receive_waits_in_poll(pair):
    a, b = pair
    to = b.sock.getsockname()
    b.sock = sock = Counting(b.sock, refuse_options=True)
    b._readable = polls = Counting(b._readable)
    buffer = memoryview(bytearray(65_537))
    start = time.monotonic()
    assert b.receive_into(buffer, 0.05) is None
    assert time.monotonic() - start >= 0.045
    assert b._timeout is False
    sent = [os.urandom(n) for n in (10, 5_000, 60_000)]
    for datagram in sent:
        a.send(datagram, to)
    got = []
    for _ in sent:
        one = b.receive_into(buffer, 2.0)
        assert one is not None
        got.append(bytes(buffer[:one[0]]))
    assert got == sent
    assert sock.calls == {"setsockopt": 1, "recvmsg_into": 3}  # tried once, then never again
    assert polls.calls == {"poll": 4}
