"""The ``can`` transport on its own, as its author tests it: real python-can ``virtual`` buses
(in-process), a raw python-can bus on the same channel watching what goes on the wire.

End-to-end tests (two rosgate engines, ROS messages) are in the rosgate repository's
tests/test_transport_can.py."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys

import can
import pytest
from rosgate_transport_can import CanTransport, rosgate_transports

from rosgate import DatagramTransport, LinkError, OptionError

_channels = itertools.count()


@pytest.fixture
def channel():
    return f"can-unit-{os.getpid()}-{next(_channels)}"


@pytest.fixture
def closing():
    things = []
    yield lambda thing: things.append(thing) or thing
    for thing in reversed(things):
        thing.close() if hasattr(thing, "close") else thing.shutdown()


@pytest.fixture
def wire(channel, closing):
    """A raw python-can bus on the channel: sees every frame, sends any frame."""
    return closing(can.Bus(interface="virtual", channel=channel))


def transport(channel, **options) -> CanTransport:
    return CanTransport({"interface": "virtual", "channel": channel, **options})


def test_registers_through_the_rosgate_hook():
    registered = []
    rosgate_transports(register=registered.append)
    assert registered == [CanTransport]
    assert (CanTransport.name, issubclass(CanTransport, DatagramTransport)) == ("can", True)


def test_python_can_is_imported_only_when_a_bus_is_asked_for():
    code = "import sys, rosgate_transport_can; print('can' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60)
    assert result.stdout.strip() == "False", result.stderr


def test_arbitration_id_is_base_id_plus_port_byte_exact(channel, wire, closing):
    endpoint = closing(transport(channel).bind(("can0", 0)))
    endpoint.send(b"\x80\x02hi", ("anything: the host means nothing on a bus", 5))
    message = wire.recv(2)
    assert (message.arbitration_id, bytes(message.data)) == (0x105, b"\x80\x02hi")
    assert (message.is_extended_id, message.is_fd) == (False, False)


def test_extended_ids(channel, wire, closing):
    endpoint = closing(transport(channel, base_id=0x18FF0000, extended=True).bind(("", 0)))
    endpoint.send(b"x", ("", 0x20))
    message = wire.recv(2)
    assert (message.arbitration_id, message.is_extended_id) == (0x18FF0020, True)


@pytest.mark.parametrize("size, padded", [(8, 8), (9, 12), (50, 64), (64, 64)])
def test_can_fd_frames_are_padded_to_a_valid_length(channel, wire, closing, size, padded):
    fd = transport(channel, fd=True, bitrate=500000, data_bitrate=2000000)
    assert fd.max_frame == 64
    endpoint = closing(fd.bind(("", 0)))
    endpoint.send(bytes(range(1, size + 1)), ("", 1))
    message = wire.recv(2)
    assert bytes(message.data) == bytes(range(1, size + 1)) + bytes(padded - size)
    assert (message.is_fd, message.bitrate_switch) == (True, True)


def test_a_port_receives_its_id_only(channel, wire, closing):
    t = transport(channel)
    assert t.max_frame == 8
    five, six = closing(t.bind(("can0", 5))), closing(t.bind(("can0", 6)))
    standard = {"is_extended_id": False}  # python-can's Message defaults to extended ids
    for message in [can.Message(arbitration_id=0x104, data=b"4", **standard),
                    can.Message(arbitration_id=0x105, data=b"5", is_extended_id=True),
                    can.Message(arbitration_id=0x105, is_remote_frame=True, **standard),
                    can.Message(arbitration_id=0x105, is_error_frame=True, **standard),
                    can.Message(arbitration_id=0x106, data=b"6", **standard),
                    can.Message(arbitration_id=0x105, data=b"five", **standard)]:
        wire.send(message)
    assert five.receive(2) == (b"five", (channel, 5))
    assert six.receive(2) == (b"6", (channel, 6))
    assert five.receive(0.05) is None and six.receive(0.05) is None


def test_a_node_does_not_hear_its_own_frames(channel, closing):
    # as on a real bus (and python-can's receive_own_messages default): one bus per engine
    t = transport(channel)
    endpoint = closing(t.bind(("", 5)))
    endpoint.send(b"mine", ("", 5))
    assert endpoint.receive(0.2) is None


def test_one_bus_per_transport_however_many_ports(channel):
    t = transport(channel)
    first, second, third = (t.bind(("", port)) for port in (0, 1, 2))
    assert len(can.interfaces.virtual.channels[channel]) == 1
    with pytest.raises(LinkError, match=r"arbitration id 0x101 \(port 1\) is already bound"):
        t.bind(("", 1))
    for endpoint in (second, second, third):  # closing twice gives up one share only
        endpoint.close()
        assert len(can.interfaces.virtual.channels[channel]) == 1
    first.close()
    assert channel not in can.interfaces.virtual.channels  # the last close shut the bus
    with pytest.raises(OSError, match="the CAN bus is closed"):
        first.send(b"late", ("", 1))
    t.bind(("", 1)).close()  # and it opens again


def test_ports_past_the_last_id(channel, closing):
    t = transport(channel, base_id=0x7F0)
    with pytest.raises(LinkError, match="port 16 is arbitration id 0x800, past the last standard"):
        t.bind(("", 16))
    endpoint = closing(t.bind(("", 15)))
    with pytest.raises(OSError, match="port 16 is arbitration id 0x800"):
        endpoint.send(b"x", ("", 16))


def test_python_can_errors_become_link_errors():
    t = CanTransport({"interface": "socketcan", "channel": "rosgate-nope0"})
    with pytest.raises(LinkError, match="python-can cannot open socketcan channel rosgate-nope0: "):
        t.bind(("", 1))


@pytest.mark.parametrize("options, key, message", [
    ({"bitrate": "500k"}, "bitrate", "expected an integer >= 1 or null, got '500k'"),
    ({"bitrate": True}, "bitrate", "expected an integer >= 1 or null, got true (a boolean)"),
    ({"data_bitrate": 0}, "data_bitrate", "expected an integer >= 1 or null, got 0"),
    ({"fd": 1}, "fd", "expected true or false, got 1"),
    ({"extended": "yes"}, "extended", "expected true or false, got 'yes'"),
    ({"interface": "vcan"}, "interface", "python-can has no interface 'vcan'"),
    ({"base_id": -1}, "base_id", "must be an arbitration id from 0 to 2046"),
    ({"base_id": 0x7FF}, "base_id", "must be an arbitration id from 0 to 2046"),
    ({"base_id": "0x100"}, "base_id", "expected an integer, got '0x100'"),
    ({"bus": {"bitrate": 500000}}, "bus", "bitrate is an option of its own"),
    ({"bus": []}, "bus", "expected a mapping, got a list []"),
    ({"bitrates": 1}, "bitrates", "unknown key 'bitrates' (did you mean 'bitrate'?)"),
], ids=["bitrate-text", "bitrate-bool", "data_bitrate-0", "fd-int", "extended-text",
        "interface", "base_id-negative", "base_id-last", "base_id-text",
        "bus-named", "bus-list", "unknown"])
def test_wrong_options(options, key, message):
    with pytest.raises(OptionError) as error:
        CanTransport({"interface": "virtual", **options})
    assert (error.value.key, error.value.message[:len(message)]) == (key, message)


def test_extended_ids_take_a_base_id_past_the_standard_ones():
    t = CanTransport({"interface": "virtual", "base_id": 0x7FF, "extended": True})
    assert (t.options.base_id, t.max_id) == (0x7FF, 0x1FFFFFFF)


def test_bus_arguments_reach_can_bus_beside_the_named_ones():
    t = CanTransport({"interface": "virtual", "channel": "c", "fd": True,
                      "bus": {"receive_own_messages": True}})
    assert t.bus_options == {"interface": "virtual", "channel": "c", "fd": True,
                             "receive_own_messages": True}
    assert CanTransport({"interface": "virtual"}).bus_options == {"interface": "virtual"}


def test_an_unknown_interface_lists_the_known_ones():
    with pytest.raises(OptionError) as error:
        CanTransport({"interface": "vcan"})
    assert "socketcan" in error.value.fix and "virtual" in error.value.fix
