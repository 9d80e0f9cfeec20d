"""The bt transport alone. Its address notation and checks, its options, the plain error on a
Python without Bluetooth, and its stream path (listen, accept, connect, bytes both ways, a busy
channel, a channel left by a dead listener) over its AF_UNIX stand-in for a radio. What the
stand-in cannot show — RFCOMM itself — is said in the README."""

from __future__ import annotations

import itertools
import socket
import tempfile

import pytest
import rosgate_transport_bt
from rosgate_testing import TransportConformance
from rosgate_transport_bt import BluetoothTransport

from rosgate import LinkError, OptionError

NO_RADIO = not hasattr(socket, "AF_BLUETOOTH")


@pytest.fixture
def bt():
    with tempfile.TemporaryDirectory(prefix="bt", dir="/tmp") as directory:  # short: AF_UNIX paths
        yield BluetoothTransport({"emulate_dir": directory})


@pytest.mark.parametrize("text, address", [
    ("AA:BB:CC:DD:EE:FF/5", ("AA:BB:CC:DD:EE:FF", 5)),
    ("aa:bb:cc:dd:ee:0f/1", ("AA:BB:CC:DD:EE:0F", 1)),
    (" 00:00:00:00:00:00/30 ", ("00:00:00:00:00:00", 30)),
])
def test_parse_address_accepts(bt, text, address):
    assert bt.parse_address(text) == address


@pytest.mark.parametrize("text, says", [
    ("AA:BB:CC:DD:EE:FF", "is not a device address and an RFCOMM channel"),
    ("AA:BB:CC:DD:EE:FF:5", "is not a device address and an RFCOMM channel"),
    ("127.0.0.1:12000", "is not a device address and an RFCOMM channel"),
    ("AA:BB:CC:DD:EE/5", "'AA:BB:CC:DD:EE' is not a Bluetooth device address"),
    ("AA:BB:CC:DD:EE:GG/5", "is not a Bluetooth device address"),
    ("AA:BB:CC:DD:EE:FF/0", "RFCOMM channel 0 is out of range: channels are 1 to 30"),
    ("AA:BB:CC:DD:EE:FF/31", "RFCOMM channel 31 is out of range"),
    ("AA:BB:CC:DD:EE:FF/x", "is not a device address and an RFCOMM channel"),
])
def test_parse_address_rejects_with_the_notation(bt, text, says):
    with pytest.raises(ValueError) as info:
        bt.parse_address(text)
    assert says in str(info.value)


def test_check_address_validates_addresses_the_core_builds(bt):
    """A topic's (server host, port): the host must be a device address, the port a channel."""
    assert bt.check_address(("aa:bb:cc:dd:ee:ff", 12)) == ("AA:BB:CC:DD:EE:FF", 12)
    with pytest.raises(ValueError, match="'127.0.0.1' is not a Bluetooth device address"):
        bt.check_address(("127.0.0.1", 12))
    with pytest.raises(ValueError, match="channel 12001 is out of range"):
        bt.check_address(("AA:BB:CC:DD:EE:FF", 12001))


@pytest.mark.parametrize("options, key, says", [
    ({"channel": 3}, "channel", "unknown key 'channel'"),
    ({"emulate_dir": 5}, "emulate_dir", "expected a string or null, got 5"),
    ({"emulate_dir": ""}, "emulate_dir", "must be a directory path"),
])
def test_bad_options(options, key, says):
    with pytest.raises(OptionError) as info:
        BluetoothTransport(options)
    assert info.value.key == key and says in info.value.message


@pytest.mark.skipif(not NO_RADIO, reason="this Python has socket.AF_BLUETOOTH")
def test_without_bluetooth_support_the_error_says_what_to_install():
    with pytest.raises(OptionError) as info:
        BluetoothTransport({})
    assert info.value.key is None
    assert "built without Bluetooth support (socket.AF_BLUETOOTH)" in info.value.message
    assert "libbluetooth-dev" in info.value.message
    with pytest.raises(LinkError, match="built without Bluetooth support"):
        rosgate_transport_bt.rfcomm_socket()


def test_emulated_stream_carries_bytes_both_ways(bt):
    listener = bt.listen(("AA:BB:CC:DD:EE:01", 4))
    try:
        client = bt.connect(("aa:bb:cc:dd:ee:01", 4), 2.0)
        accepted = listener.accept(2.0)
        assert accepted is not None
        server, peer = accepted
        assert peer == ("00:00:00:00:00:00", 0)  # an unnamed socket: who is unknown
        client.send(b"\x00ping\xff")
        assert server.receive(100, 2.0) == b"\x00ping\xff"
        server.send(b"pong")
        assert client.receive(100, 2.0) == b"pong"
        client.close()
        assert server.receive(100, 2.0) == b""
        server.close()
    finally:
        listener.close()


def test_a_busy_channel_is_refused_and_a_dead_listeners_is_reclaimed(bt):
    address = ("AA:BB:CC:DD:EE:02", 9)
    listener = bt.listen(address)
    with pytest.raises(LinkError, match="cannot listen on RFCOMM AA:BB:CC:DD:EE:02/9"):
        bt.listen(address)
    listener.close()  # its socket file stays behind, as after a crash
    bt.listen(address).close()


def test_connect_to_nobody_raises_oserror(bt):
    with pytest.raises(OSError):
        bt.connect(("AA:BB:CC:DD:EE:03", 1), 1.0)


class TestBluetoothConformance(TransportConformance):
    """The kit's stream-link contract, over the AF_UNIX stand-in for a radio."""

    transport = BluetoothTransport

    @pytest.fixture
    def plugin(self, bt) -> BluetoothTransport:
        return bt

    @pytest.fixture
    def address(self):
        channels = itertools.count(1)
        return lambda: ("AA:BB:CC:DD:EE:10", next(channels))

