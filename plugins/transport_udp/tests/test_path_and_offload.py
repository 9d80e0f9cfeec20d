"""udp's frame size from the path, and the kernel's segmentation and receive offload.

max_frame: the route's MTU less the IP and UDP headers where the file does not set it (65,000,
the most, on loopback; 1,472 on a veth pair, Ethernet's 1,500, between two network namespaces;
the same for a server binding its own address there), the file's value as an upper bound, 1,200
where the path is not known, said once in the log.

Offload: a frame's fragments leave in one sendmsg and arrive in one receive where the kernel
can, and exactly the same datagrams arrive, in order, where it cannot (``offload: false``, or a
path that refuses segmentation: the endpoint falls back by itself)."""

from __future__ import annotations

import errno
import logging
import random

import pytest
from rosgate_emulator import NetnsPair
from rosgate_transport_udp import DEFAULT_FRAME, UdpEndpoint, UdpTransport, path_frame


@pytest.fixture
def closing():
    things = []
    yield lambda thing: things.append(thing) or thing
    for thing in reversed(things):
        thing.close()


# --- max_frame from the path -----------------------------------------------------------------

def test_on_loopback_max_frame_is_the_most_the_option_takes(caplog):
    transport = UdpTransport({})
    assert transport.max_frame == DEFAULT_FRAME == 1_200  # nothing known yet
    with caplog.at_level(logging.INFO, logger="rosgate.udp"):
        assert transport.check_address(("127.0.0.1", 5000)) == ("127.0.0.1", 5000)
        transport.check_address(("127.0.0.1", 5001))  # the same path: nothing new to say
    assert path_frame("127.0.0.1") == (65_535, 65_507)  # IPv4 loopback: at most 65,535
    assert transport.max_frame == 65_000
    said = [r.getMessage() for r in caplog.records if "max_frame" in r.getMessage()]
    assert said == ["udp: max_frame 65000 bytes, from the path to 127.0.0.1 (MTU 65535 less 28 "
                    "bytes of IP and UDP headers, at most 65000)"]


def test_a_max_frame_in_the_file_is_an_upper_bound(caplog):
    transport = UdpTransport({"max_frame": 1472})
    assert transport.max_frame == 1472
    with caplog.at_level(logging.INFO, logger="rosgate.udp"):
        transport.check_address(("127.0.0.1", 5000))
    assert transport.max_frame == 1472  # the path would take more; the file says no more
    assert any("at most 1472 as the file says" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("host", ["0.0.0.0", "::"])
def test_where_the_path_is_not_known_max_frame_fits_every_path(host, caplog):
    transport = UdpTransport({})
    with caplog.at_level(logging.INFO, logger="rosgate.udp"):
        transport.check_address((host, 5000))
    assert path_frame(host) is None
    assert transport.max_frame == 1_200
    assert not [r for r in caplog.records if "max_frame" in r.getMessage()]


def test_the_smallest_path_seen_wins():
    transport = UdpTransport({})
    transport.paths["192.0.2.7"] = 1_372  # as if seen: a path of MTU 1,400
    transport.check_address(("127.0.0.1", 5000))
    assert transport.max_frame == 1_372


@pytest.mark.skipif(NetnsPair.unavailable() is not None, reason=str(NetnsPair.unavailable()))
def test_over_a_veth_pair_max_frame_fills_an_ethernet_frame():
    """Two network namespaces joined by a veth pair (MTU 1,500): the side that sends to the
    other, and the side that binds its own address there (a server), both get 1,472."""
    with NetnsPair() as pair:
        with pair.inside("a"):
            client = UdpTransport({})
            client.check_address((pair.address("b"), 5000))
        with pair.inside("b"):
            server = UdpTransport({})
            server.check_address((pair.address("b"), 5000))  # its own: the interface's MTU
            loopback = path_frame("127.0.0.1")
        assert client.max_frame == server.max_frame == 1_472
        assert loopback == (65_535, 65_507)  # the namespace's own loopback is still loopback


# --- segmentation and receive offload ----------------------------------------------------------

def fragments(count: int, size: int, last: int, seed: int) -> list[list[bytes]]:
    """Datagrams as the core hands them over: a header and a chunk each, the last shorter."""
    rng = random.Random(seed)
    out = []
    for i in range(count):
        length = size if i < count - 1 else last
        out.append([b"RF%012d" % i, rng.randbytes(length - 14)])
    return out


def receive_all(endpoint: UdpEndpoint, count: int) -> list[bytes]:
    buffer = memoryview(bytearray(65_537))
    got = []
    while len(got) < count:
        one = endpoint.receive_into(buffer, 2.0)
        assert one is not None, f"{len(got)} of {count} arrived"
        got.append(bytes(buffer[:one[0]]))
    return got


class Counting:
    """A socket stand-in that counts sendmsg calls (and can refuse segmentation as a device
    without checksum offload does: EIO)."""

    def __init__(self, sock, refuse_segments: bool = False):
        self.sock = sock
        self.calls = 0
        self.refuse = refuse_segments

    def sendmsg(self, parts, ancillary=(), flags=0, to=None):
        self.calls += 1
        if self.refuse and ancillary:
            raise OSError(errno.EIO, "Input/output error")
        return self.sock.sendmsg(parts, ancillary, flags, to)

    def __getattr__(self, name):
        return getattr(self.sock, name)


@pytest.mark.parametrize("offload", [True, False], ids=["offload", "one-call-per-datagram"])
def test_a_frames_datagrams_arrive_whole_and_in_order(closing, offload):
    transport = UdpTransport({"offload": offload})
    a = closing(transport.bind(("127.0.0.1", 0)))
    b = closing(transport.bind(("127.0.0.1", 0)))
    counting = a.sock = Counting(a.sock)
    datagrams = fragments(130, 1_200, 517, seed=1)  # more than one segmented send carries
    a.send_datagrams(datagrams, b.sock.getsockname())
    got = receive_all(b, len(datagrams))
    assert got == [b"".join(d) for d in datagrams]
    if offload:
        assert a.gso is True and b.gro is True
        # 64 datagrams at most per call, and at most 65,000 bytes: 54 of 1,200
        assert counting.calls == 3
    else:
        assert a.gso is False and b.gro is False
        assert counting.calls == 130
    assert b.receive_into(memoryview(bytearray(65_537)), 0.05) is None  # nothing more


def test_a_path_that_refuses_segmentation_falls_back_once_and_loses_nothing(closing, caplog):
    transport = UdpTransport({})
    a = closing(transport.bind(("127.0.0.1", 0)))
    b = closing(transport.bind(("127.0.0.1", 0)))
    counting = a.sock = Counting(a.sock, refuse_segments=True)
    first, second = fragments(5, 1_200, 300, seed=2), fragments(4, 1_200, 1_200, seed=3)
    with caplog.at_level(logging.INFO, logger="rosgate.udp"):
        a.send_datagrams(first, b.sock.getsockname())
        a.send_datagrams(second, b.sock.getsockname())
    assert a.gso is False
    assert counting.calls == 1 + 5 + 4  # the refused try, then one per datagram
    assert receive_all(b, 9) == [b"".join(d) for d in first + second]
    assert [r.getMessage() for r in caplog.records if "offload" in r.getMessage()] == [
        "udp: segmentation offload failed (Input/output error): one system call per datagram"]


def test_an_error_that_is_not_about_segmentation_reaches_the_core(closing):
    """A datagram the kernel refuses for what it is (too long for IPv4) is the caller's error
    (the core counts it: send_error), not a reason to give up offload."""
    transport = UdpTransport({})
    a = closing(transport.bind(("127.0.0.1", 0)))
    b = closing(transport.bind(("127.0.0.1", 0)))
    with pytest.raises(OSError):
        a.send_datagrams([[bytes(65_508)], [bytes(10)]], b.sock.getsockname())
    assert a.gso is None  # still untried


def test_datagrams_of_different_sizes_each_leave_as_they_are(closing):
    """Only a run of equal sizes (the last shorter) is one segmented send; a longer one after a
    shorter one starts the next run."""
    transport = UdpTransport({})
    a = closing(transport.bind(("127.0.0.1", 0)))
    b = closing(transport.bind(("127.0.0.1", 0)))
    datagrams = [[b"x" * 500], [b"y" * 500], [b"z" * 200], [b"w" * 900], [b"v" * 100]]
    a.send_datagrams(datagrams, b.sock.getsockname())
    assert receive_all(b, 5) == [b"".join(d) for d in datagrams]


def test_receive_returns_joined_datagrams_one_by_one(closing):
    transport = UdpTransport({})
    a = closing(transport.bind(("127.0.0.1", 0)))
    b = closing(transport.bind(("127.0.0.1", 0)))
    datagrams = fragments(6, 1_000, 250, seed=4)
    a.send_datagrams(datagrams, b.sock.getsockname())
    got = [b.receive(2.0) for _ in datagrams]
    assert [g[0] for g in got if g] == [b"".join(d) for d in datagrams]
    assert {g[1] for g in got if g} == {a.sock.getsockname()}
