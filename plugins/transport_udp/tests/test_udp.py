"""The udp transport alone, with real sockets on loopback: the plugin kit's conformance suite
(frames cross byte-exact up to max_frame and beyond, boundaries, idle receive, close), then
what is particular to UDP: the IPv4 size limit, IPv6, busy ports, kernel buffers, options."""

from __future__ import annotations

import os
import socket

import pytest
from rosgate_testing import TransportConformance, has_ipv6_loopback
from rosgate_transport_udp import UdpTransport

from rosgate import LinkError, OptionError


class TestUdpConformance(TransportConformance):
    transport = UdpTransport


@pytest.fixture
def endpoints():
    """Bind endpoints through this; all are closed after the test."""
    opened = []
    transport = UdpTransport({})

    def bind(host: str = "127.0.0.1", port: int = 0, transport: UdpTransport = transport):
        endpoint = transport.bind((host, port))
        opened.append(endpoint)
        return endpoint, endpoint.sock.getsockname()[:2]

    yield bind
    for endpoint in opened:
        endpoint.close()


def test_bind_on_port_0_picks_a_port(endpoints):
    _, (host, port) = endpoints()
    assert host == "127.0.0.1" and 0 < port < 65536


def test_a_datagram_over_the_ipv4_limit_cannot_be_sent(endpoints):
    # the largest max_frame the option takes is below the limit, with room to spare
    assert UdpTransport({"max_frame": 65_000}).max_frame == 65_000
    with pytest.raises(OptionError, match=r"expected an integer 256\.\.65000 or null, got 65001"):
        UdpTransport({"max_frame": 65_001})
    a, _ = endpoints()
    _, b_address = endpoints()
    with pytest.raises(OSError):
        a.send(bytes(65_508), b_address)


def test_binding_a_port_in_use_names_the_port(endpoints):
    _, (_, port) = endpoints()
    with pytest.raises(LinkError) as info:
        endpoints("127.0.0.1", port)
    assert f"127.0.0.1:{port}" in str(info.value)
    assert "in use" in str(info.value)


def test_binding_an_address_not_on_this_machine(endpoints):
    with pytest.raises(LinkError, match="192.0.2.1"):
        endpoints("192.0.2.1", 0)  # TEST-NET-1, never local


@pytest.mark.skipif(not has_ipv6_loopback(), reason="the kernel has no IPv6 loopback (::1)")
def test_ipv6_loopback(endpoints):
    a, a_address = endpoints("::1")
    b, b_address = endpoints("::1")
    assert a.sock.family == socket.AF_INET6
    a.send(b"over six", b_address)
    assert b.receive(2.0) == (b"over six", a_address)
    assert a_address[0] == "::1"


# --- options and addresses -----------------------------------------------------------------------

def test_unknown_option():
    with pytest.raises(OptionError) as info:
        UdpTransport({"receive_buffer": 1 << 20, "recv_buffer": 1, "zz": 2})
    assert info.value.key == "recv_buffer"
    assert info.value.message == "unknown key 'recv_buffer' (did you mean 'receive_buffer'?)"
    assert info.value.fix == "valid keys are receive_buffer, send_buffer, max_frame, offload"


def test_max_frame_defaults_to_a_size_every_path_carries():
    """1,200 bytes: IPv6's minimum MTU (1,280) less its headers leaves 1,232; a datagram over the
    path's MTU travels as IP fragments and is lost with any one of them."""
    assert UdpTransport({}).max_frame == UdpTransport.max_frame == 1_200
    assert UdpTransport({"max_frame": 1472}).max_frame == 1472
    with pytest.raises(OptionError, match=r"expected an integer 256\.\.65000 or null, got 100"):
        UdpTransport({"max_frame": 100})


@pytest.mark.parametrize("key", ["receive_buffer", "send_buffer"])
@pytest.mark.parametrize("value, message", [
    (0, "expected an integer >= 1, got 0"), (-1, "expected an integer >= 1, got -1"),
    ("4M", "expected an integer >= 1, got '4M'"), (1.5, "expected an integer >= 1, got 1.5"),
    (True, "expected an integer >= 1, got true (a boolean)"),
    (None, "expected an integer >= 1, got nothing")])
def test_buffer_sizes_must_be_positive_integers(key, value, message):
    with pytest.raises(OptionError) as info:
        UdpTransport({key: value})
    assert info.value.key == key
    assert info.value.message == message


def test_buffer_sizes_are_asked_of_the_kernel(endpoints):
    size = 256 * 1024
    transport = UdpTransport({"receive_buffer": size, "send_buffer": size})
    assert (transport.options.receive_buffer, transport.options.send_buffer) == (size, size)
    endpoint, _ = endpoints(transport=transport)
    # Linux reports twice what it grants; without privilege it is capped by rmem_max / wmem_max
    caps = {}
    for option, name in [(socket.SO_RCVBUF, "rmem_max"), (socket.SO_SNDBUF, "wmem_max")]:
        with open(f"/proc/sys/net/core/{name}") as f:
            caps[option] = int(f.read())
    for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        if caps[option] < size and not _privileged():
            continue
        assert endpoint.sock.getsockopt(socket.SOL_SOCKET, option) // 2 >= size


def test_as_root_a_buffer_beyond_the_system_limit_is_granted(endpoints):
    if not _privileged():
        pytest.skip("forcing a buffer past rmem_max needs root (CAP_NET_ADMIN)")
    with open("/proc/sys/net/core/rmem_max") as f:
        size = 2 * int(f.read()) + 4096
    endpoint, _ = endpoints(transport=UdpTransport({"receive_buffer": size}))
    assert endpoint.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) // 2 >= size


def test_a_capped_buffer_is_warned_about_once_with_the_fix(endpoints, monkeypatch, caplog):
    import rosgate_transport_udp as udp

    monkeypatch.setattr(udp, "_warned", set())
    monkeypatch.setitem(udp._FORCE, socket.SO_RCVBUF, None)  # as a process without privilege
    with open("/proc/sys/net/core/rmem_max") as f:
        cap = int(f.read())
    size = 2 * cap + 4096
    transport = UdpTransport({"receive_buffer": size})
    with caplog.at_level("WARNING", logger="rosgate.udp"):
        endpoints(transport=transport)
        endpoints(transport=transport)
    warnings = [r.getMessage() for r in caplog.records if "receive buffer" in r.getMessage()]
    assert len(warnings) == 1
    assert f"not the {size} asked for (net.core.rmem_max caps it)" in warnings[0]
    assert f"sysctl -w net.core.rmem_max={2 * size}" in warnings[0]


def _privileged() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.mark.parametrize("text, address", [
    ("127.0.0.1:12000", ("127.0.0.1", 12000)),
    ("[::1]:12000", ("::1", 12000)),
    (" 192.168.1.20:1 ", ("192.168.1.20", 1)),
    ("robot.local:65535", ("robot.local", 65535)),
])
def test_parse_address_accepts(text, address):
    assert UdpTransport({}).parse_address(text) == address


@pytest.mark.parametrize("text", ["127.0.0.1", "host:0", "host:70000", "host:65536", ":12000",
                                  "host:", "host:12a", "host:-1", "", "[::1]", "[]:12000"])
def test_parse_address_rejects(text):
    with pytest.raises(ValueError, match="is not host:port"):
        UdpTransport({}).parse_address(text)
