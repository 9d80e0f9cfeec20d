"""The tcp transport alone, with real sockets on loopback: bytes cross both ways unchanged, the end
of a connection and an idle one are told apart, close() unblocks a receive, and busy ports and
bad options are refused with a clear error."""

from __future__ import annotations

import random
import socket
import threading
import time

import pytest

import rosgate_transport_tcp
from rosgate import LinkError, OptionError
from rosgate.plugins import Plugins
from rosgate_transport_tcp import TcpConnection, TcpTransport


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def has_ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


def wait_until_blocked(native_id: int, timeout: float = 2.0) -> None:
    """Wait until a thread sleeps in poll() (a socket receive with a timeout), as Linux reports it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/self/task/{native_id}/wchan") as f:
                if "poll" in f.read():
                    return
        except OSError:
            pytest.skip("cannot see where a thread sleeps (/proc/self/task/*/wchan)")
        time.sleep(0.01)
    pytest.fail("the receive never blocked")


def receive_exactly(connection: TcpConnection, size: int, timeout: float = 5.0) -> bytes:
    data = bytearray()
    deadline = time.monotonic() + timeout
    while len(data) < size:
        left = deadline - time.monotonic()
        assert left > 0, f"only {len(data)} of {size} bytes within {timeout} s"
        chunk = connection.receive(size - len(data), left)
        assert chunk != b"", f"closed after {len(data)} of {size} bytes"
        if chunk:
            data += chunk
    return bytes(data)


@pytest.fixture
def closing():
    """Register connections and listeners to close after the test."""
    things = []
    yield lambda thing: things.append(thing) or thing
    for thing in reversed(things):
        thing.close()


@pytest.fixture
def pair(closing):
    """A connected (client, server) pair of TcpConnections on 127.0.0.1."""
    transport = TcpTransport({})
    port = free_port()
    listener = closing(transport.listen(("127.0.0.1", port)))
    client = closing(transport.connect(("127.0.0.1", port), 2.0))
    accepted = listener.accept(2.0)
    assert accepted is not None
    server, peer = accepted
    closing(server)
    assert peer == client.sock.getsockname()[:2]
    return client, server


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


def test_accept_returns_none_when_nobody_connects(closing):
    listener = closing(TcpTransport({}).listen(("127.0.0.1", 0)))
    started = time.monotonic()
    assert listener.accept(0.2) is None
    assert 0.15 < time.monotonic() - started < 2.0


def test_bytes_cross_both_ways(pair):
    client, server = pair
    rng = random.Random(1)
    small = rng.randbytes(100)
    client.send(small)
    assert receive_exactly(server, len(small)) == small
    server.send(b"\x00pong\xff")
    assert receive_exactly(client, 6) == b"\x00pong\xff"


def test_a_megabyte_each_way_at_the_same_time(pair):
    client, server = pair
    rng = random.Random(2)
    up, down = rng.randbytes(1 << 20), rng.randbytes(1 << 20)
    errors: list[BaseException] = []

    def send(connection, data):
        try:
            connection.send(data)
        except BaseException as exc:  # reported by the test thread
            errors.append(exc)

    senders = [threading.Thread(target=send, args=(client, up)),
               threading.Thread(target=send, args=(server, down))]
    for thread in senders:
        thread.start()
    got_down = receive_exactly(client, len(down))
    got_up = receive_exactly(server, len(up))
    for thread in senders:
        thread.join(5)
    assert errors == []
    assert got_up == up and got_down == down


def test_receive_honours_max_bytes(pair):
    client, server = pair
    client.send(b"abcdefgh")
    first = server.receive(3, 2.0)
    assert first and len(first) <= 3
    assert first + receive_exactly(server, 8 - len(first)) == b"abcdefgh"


def test_receive_returns_none_on_timeout(pair):
    _, server = pair
    started = time.monotonic()
    assert server.receive(1024, 0.2) is None
    assert 0.15 < time.monotonic() - started < 2.0


def test_receive_returns_empty_after_the_far_end_closes(pair):
    client, server = pair
    client.send(b"last words")
    client.close()
    assert receive_exactly(server, 10) == b"last words"
    assert server.receive(1024, 2.0) == b""
    assert server.receive(1024, 2.0) == b""  # and stays so


def test_send_after_the_far_end_closed_raises_oserror(pair):
    client, server = pair
    client.close()
    assert server.receive(1024, 2.0) == b""
    with pytest.raises(OSError):
        for _ in range(100):  # the first write may still be accepted by the kernel
            server.send(b"x" * 65536)


def test_close_from_another_thread_ends_a_blocked_receive(pair):
    _, server = pair
    result: list[object] = []
    native_id: list[int] = []
    finished = threading.Event()

    def receive():
        native_id.append(threading.get_native_id())
        try:
            result.append(server.receive(1024, 30.0))
        except OSError as exc:
            result.append(exc)
        finished.set()

    thread = threading.Thread(target=receive, daemon=True)
    thread.start()
    while not native_id:
        time.sleep(0.001)
    wait_until_blocked(native_id[0])
    closed_at = time.monotonic()
    server.close()
    assert finished.wait(2.0), "receive still blocked 2 s after close"
    assert time.monotonic() - closed_at < 2.0
    assert result[0] == b"" or isinstance(result[0], OSError), result
    thread.join()


def test_connect_to_a_closed_port_raises_oserror():
    port = free_port()
    with pytest.raises(OSError):
        TcpTransport({}).connect(("127.0.0.1", port), 2.0)


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


# --- options and addresses ----------------------------------------------------------------------------

def nodelay(connection: TcpConnection) -> bool:
    return connection.sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0


@pytest.mark.parametrize("options, expected", [({}, True), ({"nodelay": True}, True),
                                               ({"nodelay": False}, False)])
def test_nodelay_is_set_on_both_ends(closing, options, expected):
    transport = TcpTransport(options)
    assert transport.nodelay is expected
    listener = closing(transport.listen(("127.0.0.1", 0)))
    client = closing(transport.connect(listener.sock.getsockname(), 2.0))
    server, _ = listener.accept(2.0)
    closing(server)
    assert nodelay(client) is expected
    assert nodelay(server) is expected


@pytest.mark.parametrize("value", ["yes", 1, 0, None, "true"])
def test_nodelay_must_be_a_boolean(value):
    with pytest.raises(OptionError) as info:
        TcpTransport({"nodelay": value})
    assert info.value.key == "nodelay"
    assert repr(value) in info.value.message


def test_unknown_option():
    with pytest.raises(OptionError) as info:
        TcpTransport({"nodelay": True, "no_delay": True})
    assert info.value.key == "no_delay"
    assert info.value.message == "unknown option of tcp"


@pytest.mark.parametrize("text, address", [
    ("127.0.0.1:12000", ("127.0.0.1", 12000)),
    ("[::1]:12000", ("::1", 12000)),
    ("server:1", ("server", 1)),
])
def test_parse_address_accepts(text, address):
    assert TcpTransport({}).parse_address(text) == address


@pytest.mark.parametrize("text", ["127.0.0.1", "host:0", "host:70000", ":12000", "host:", "host:port"])
def test_parse_address_rejects(text):
    with pytest.raises(ValueError, match="is not host:port"):
        TcpTransport({}).parse_address(text)


def test_registered_through_its_hook():
    plugins = Plugins()
    plugins.add(rosgate_transport_tcp, "tcp", "rosgate-transport-tcp", "0.1.0")
    assert plugins.failures == []
    registration = plugins.get("transport", "tcp")
    assert registration.cls is TcpTransport and registration.cls.stream is True


def test_sending_while_a_receive_waits_does_not_break_the_receive(pair):
    """Links send and receive on one connection from two threads (service calls and answers)."""
    a, b = pair
    errors: list[BaseException] = []
    stop = threading.Event()

    def receive_all() -> None:
        try:
            while not stop.is_set():
                a.receive(65536, 0.0001)  # short waits: many chances to collide with a send
        except BaseException as exc:  # noqa: BLE001 - any failure is the finding
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
