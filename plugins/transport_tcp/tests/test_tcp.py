"""The tcp transport alone, with real sockets on loopback: the plugin kit's conformance suite
(bytes both ways, the end of a connection and an idle one told apart, close unblocks a receive,
frames through the core), then what is particular to TCP: busy ports, TIME_WAIT, IPv6,
nodelay, options and addresses."""

from __future__ import annotations

import socket
import threading

import pytest
from rosgate_testing import TransportConformance, free_port, has_ipv6_loopback, receive_exactly
from rosgate_transport_tcp import TcpConnection, TcpTransport

from rosgate import LinkError, OptionError


class TestTcpConformance(TransportConformance):
    transport = TcpTransport


@pytest.fixture
def closing():
    """Register connections and listeners to close after the test."""
    things = []
    yield lambda thing: things.append(thing) or thing
    for thing in reversed(things):
        thing.close()


def test_listen_connect_accept(closing):
    transport = TcpTransport({})
    port = free_port()
    listener = closing(transport.listen(("127.0.0.1", port)))
    assert listener.sock.getsockname() == ("127.0.0.1", port)
    client = closing(transport.connect(("127.0.0.1", port), 2.0))
    server, peer = listener.accept(2.0)
    closing(server)
    assert peer == client.sock.getsockname()
    assert client.sock.getpeername() == ("127.0.0.1", port)


def test_listen_on_a_port_in_use_names_the_port(closing):
    transport = TcpTransport({})
    port = free_port()
    closing(transport.listen(("127.0.0.1", port)))
    with pytest.raises(LinkError) as info:
        transport.listen(("127.0.0.1", port))
    assert f"127.0.0.1:{port}" in str(info.value)
    assert "in use" in str(info.value)


def test_listen_on_a_port_left_in_time_wait_is_allowed(closing):
    # SO_REUSEADDR: a restarted server gets its port back at once
    transport = TcpTransport({})
    port = free_port()
    listener = transport.listen(("127.0.0.1", port))
    client = transport.connect(("127.0.0.1", port), 2.0)
    server, _ = listener.accept(2.0)
    server.close()  # the server side closes first: its end of the connection is in TIME_WAIT
    client.close()
    listener.close()
    closing(transport.listen(("127.0.0.1", port)))


@pytest.mark.skipif(not has_ipv6_loopback(), reason="the kernel has no IPv6 loopback (::1)")
def test_ipv6_loopback(closing):
    transport = TcpTransport({})
    listener = closing(transport.listen(("::1", 0)))
    port = listener.sock.getsockname()[1]
    client = closing(transport.connect(("::1", port), 2.0))
    server, peer = listener.accept(2.0)
    closing(server)
    assert peer[0] == "::1"
    client.send(b"six")
    assert receive_exactly(server, 3) == b"six"


# --- options and addresses -----------------------------------------------------------------------

def nodelay(connection: TcpConnection) -> bool:
    return connection.sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0


@pytest.mark.parametrize("options, expected", [({}, True), ({"nodelay": True}, True),
                                               ({"nodelay": False}, False)])
def test_nodelay_is_set_on_both_ends(closing, options, expected):
    transport = TcpTransport(options)
    assert transport.options.nodelay is expected
    listener = closing(transport.listen(("127.0.0.1", 0)))
    client = closing(transport.connect(listener.sock.getsockname(), 2.0))
    server, _ = listener.accept(2.0)
    closing(server)
    assert nodelay(client) is expected
    assert nodelay(server) is expected


@pytest.mark.parametrize("value, shown", [("yes", "'yes'"), (1, "1"), (0, "0"), (None, "nothing"),
                                          ("true", "'true'")])
def test_nodelay_must_be_a_boolean(value, shown):
    with pytest.raises(OptionError) as info:
        TcpTransport({"nodelay": value})
    assert info.value.key == "nodelay"
    assert info.value.message == f"expected true or false, got {shown}"


def test_unknown_option():
    with pytest.raises(OptionError) as info:
        TcpTransport({"nodelay": True, "no_delay": True})
    assert info.value.key == "no_delay"
    assert info.value.message == "unknown key 'no_delay' (did you mean 'nodelay'?)"


@pytest.mark.parametrize("text, address", [
    ("127.0.0.1:12000", ("127.0.0.1", 12000)),
    ("[::1]:12000", ("::1", 12000)),
    ("server:1", ("server", 1)),
])
def test_parse_address_accepts(text, address):
    assert TcpTransport({}).parse_address(text) == address


@pytest.mark.parametrize("text", ["127.0.0.1", "host:0", "host:70000", ":12000", "host:",
                                  "host:port"])
def test_parse_address_rejects(text):
    with pytest.raises(ValueError, match="is not host:port"):
        TcpTransport({}).parse_address(text)


@pytest.mark.parametrize("host", ["127.0.0.1", "::1", "fe80::1", "server", "base.local"])
def test_check_address_accepts_ip_hosts(host):
    assert TcpTransport({}).check_address((host, 1)) == (host, 1)


@pytest.mark.parametrize("host", ["AA:BB:CC:DD:EE:FF", "1:2:3", "::g"])
def test_check_address_refuses_what_is_no_ip_host(host):
    with pytest.raises(ValueError, match="is not an IP address or host name"):
        TcpTransport({}).check_address((host, 1))


@pytest.fixture
def pair():
    """Two ends of one real TCP connection."""
    transport = TcpTransport({})
    address = ("127.0.0.1", free_port())
    listener = transport.listen(address)
    a = transport.connect(address, 5.0)
    accepted = listener.accept(5.0)
    assert accepted is not None
    yield a, accepted[0]
    for end in (a, accepted[0], listener):
        end.close()


def test_sending_while_a_receive_waits_does_not_break_the_receive(pair):
    """Links send and receive on one connection from two threads (service calls and answers)."""
    a, b = pair
    errors: list[BaseException] = []
    stop = threading.Event()

    def receive_all() -> None:
        try:
            while not stop.is_set():
                a.receive(65536, 0.0001)  # short waits: many chances to collide with a send
        except BaseException as exc:  # any failure is the finding
            errors.append(exc)

    thread = threading.Thread(target=receive_all)
    thread.start()
    for _ in range(20000):
        a.send(b"x" * 10)
        if errors:
            break
    stop.set()
    thread.join()
    assert errors == []
    assert receive_exactly(b, 200000) == b"x" * 200000
