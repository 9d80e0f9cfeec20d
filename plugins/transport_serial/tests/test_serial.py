"""The serial link: the plugin kit's conformance suite over a pseudo-terminal pair, and what
is the link's own, byte for byte: its frames, its ports, a spoilt frame counted, its capacity,
an unplugged device."""

from __future__ import annotations

import itertools
import queue
import threading
import zlib

import pytest
from rosgate_emulator.serial import LineProfile, PtyRelay
from rosgate_mcu_cvra import serial_datagram
from rosgate_testing import TransportConformance
from rosgate_transport_serial import SerialTransport, line_rate

from rosgate import LinkError, OptionError

TIMEOUT = 5.0
FAST = LineProfile(baud=20_000_000)  # the kit's megabyte frames in seconds


@pytest.fixture
def relay(tmp_path):
    with PtyRelay(tmp_path, FAST) as relay:
        yield relay


class TestSerialConformance(TransportConformance):
    transport = SerialTransport
    ordered = True  # a serial line keeps order: checked

    @pytest.fixture
    def plugin(self, relay):
        return SerialTransport({"device": relay.a})

    @pytest.fixture
    def far_plugin(self, relay):
        return SerialTransport({"device": relay.b})

    @pytest.fixture
    def address(self):
        ports = itertools.count(1)
        return lambda: ("serial", next(ports))


class TestSerialConformanceLongFrames(TestSerialConformance):
    """Above 256 bytes the core cuts with fragments instead of compact pieces."""

    @pytest.fixture
    def plugin(self, relay):
        return SerialTransport({"device": relay.a, "max_frame": 1000})

    @pytest.fixture
    def far_plugin(self, relay):
        return SerialTransport({"device": relay.b, "max_frame": 1000})


def test_a_frame_on_the_line_is_ports_frame_crc_escaped(relay):
    """Byte for byte: what a peer without rosgate reads off the line."""
    import serial

    endpoint = SerialTransport({"device": relay.a}).bind(("serial", 7))
    raw = serial.Serial(relay.b, timeout=TIMEOUT)
    try:
        endpoint.send(b"\xc0hi\xdb", ("serial", 0x1234))
        body = b"\x12\x34\x00\x07\xc0hi\xdb"
        expected = serial_datagram.escape(body + zlib.crc32(body).to_bytes(4, "big")) + b"\xc0"
        assert raw.read(len(expected)) == expected
        raw.write(serial_datagram.encode(b"\x00\x07\x00\x09answer"))
        assert endpoint.receive(TIMEOUT) == (b"answer", (relay.a, 9))
    finally:
        endpoint.close()
        raw.close()


def test_bare_frames_without_ports_for_a_microcontroller(relay):
    import serial

    endpoint = SerialTransport({"device": relay.a, "multiplex": False}).bind(("serial", 1))
    raw = serial.Serial(relay.b, timeout=TIMEOUT)
    try:
        endpoint.send(bytes.fromhex("92a470696e67c0"), ("serial", 5))  # the shared vector
        expected = bytes.fromhex("92a470696e67dbdc2bdbdd6a2fc0")
        assert raw.read(len(expected)) == expected
        raw.write(serial_datagram.encode(b"pong"))
        assert endpoint.receive(TIMEOUT) == (b"pong", (relay.a, 0))
    finally:
        endpoint.close()
        raw.close()


def test_a_spoilt_frame_is_counted_and_the_next_one_arrives(relay):
    import serial

    endpoint = SerialTransport({"device": relay.a}).bind(("serial", 1))
    drops: queue.SimpleQueue = queue.SimpleQueue()
    endpoint.count_drops(lambda reason, detail: drops.put(str(reason)))
    raw = serial.Serial(relay.b, timeout=TIMEOUT)
    try:
        spoilt = bytearray(serial_datagram.encode(b"\x00\x01\x00\x02first"))
        spoilt[6] ^= 0x10
        raw.write(bytes(spoilt) + b"\x00\x01\xdb\x41\xc0"
                  + serial_datagram.encode(b"\x00\x01\x00\x02second"))
        assert endpoint.receive(TIMEOUT) == (b"second", (relay.a, 2))
        assert [drops.get(timeout=TIMEOUT), drops.get(timeout=TIMEOUT)] == \
            ["bad_crc", "bad_escape"]
        assert drops.empty()
    finally:
        endpoint.close()
        raw.close()


@pytest.mark.parametrize("options, bits", [
    ({"baud": 57600}, 57600 * 8 / 10),
    ({"baud": 9600, "parity": "even"}, 9600 * 8 / 11),
    ({"baud": 115200, "parity": "odd", "stop_bits": 2}, 115200 * 8 / 12),
    ({"baud": 19200, "stop_bits": 1.5}, 19200 * 8 / 10.5),
])
def test_capacity_counts_start_parity_and_stop_bits(options, bits):
    transport = SerialTransport({"device": "/dev/null", **options})
    assert line_rate(transport.options) == bits
    assert transport.bandwidth == 0.95 * bits  # the budget: a little below the line


@pytest.mark.parametrize("options, key", [
    ({}, "device"), ({"device": "x", "baud": 0}, "baud"),
    ({"device": "x", "parity": "yes"}, "parity"), ({"device": "x", "stop_bits": 3}, "stop_bits"),
    ({"device": "x", "flow_control": "xonxoff"}, "flow_control"),
    ({"device": "x", "max_frame": 8}, "max_frame"),
])
def test_bad_options(options, key):
    with pytest.raises(OptionError) as info:
        SerialTransport(options)
    assert info.value.key == key


def test_software_flow_control_is_refused_saying_why():
    with pytest.raises(OptionError) as info:
        SerialTransport({"device": "x", "flow_control": "xonxoff"})
    assert "XON" in str(info.value) and "rtscts" in (info.value.fix or "")


def test_garbage_on_the_line_is_counted_and_the_next_frame_arrives(relay):
    import random

    import serial

    endpoint = SerialTransport({"device": relay.a}).bind(("serial", 1))
    drops: list[str] = []
    endpoint.count_drops(lambda reason, detail: drops.append(str(reason)))
    raw = serial.Serial(relay.b, timeout=TIMEOUT)
    try:
        rng = random.Random(4)
        garbage = bytes(rng.randrange(256) for _ in range(20_000))
        raw.write(garbage + b"\xc0" + serial_datagram.encode(b"\x00\x01\x00\x02whole"))
        assert endpoint.receive(TIMEOUT) == (b"whole", (relay.a, 2))
        assert len(drops) > 10 and set(drops) <= {"bad_crc", "bad_escape", "too_short",
                                                  "too_long"}, drops
    finally:
        endpoint.close()
        raw.close()


def test_a_missing_device_is_a_link_error(tmp_path):
    with pytest.raises(LinkError) as info:
        SerialTransport({"device": str(tmp_path / "ttyUSB9")}).bind(("serial", 1))
    assert "ttyUSB9" in str(info.value) and "dialout" in (info.value.fix or "")


def test_an_answer_comes_from_the_address_the_question_went_to(relay):
    """The host of an address is only a name: the device takes its place, so an answer's source
    is the very address the question was sent to (loss recovery matches acknowledgements to
    the frames they acknowledge by it)."""
    near, far = SerialTransport({"device": relay.a}), SerialTransport({"device": relay.b})
    to = near.check_address(("line", 2))
    a, b = near.bind(near.check_address(("line", 1))), far.bind(far.check_address(("line", 2)))
    try:
        a.send(b"question", to)
        question = b.receive(TIMEOUT)
        assert question is not None and question[0] == b"question"
        b.send(b"answer", question[1])
        assert a.receive(TIMEOUT) == (b"answer", to)
    finally:
        a.close()
        b.close()


def test_unplugged_and_back_under_a_new_path(tmp_path):
    with PtyRelay(tmp_path, FAST) as relay:
        a = SerialTransport({"device": relay.a}).bind(("serial", 1))
        b = SerialTransport({"device": relay.b}).bind(("serial", 2))
        line: queue.SimpleQueue[bool] = queue.SimpleQueue()
        a.watch_line(line.put)  # what the core's link is told
        try:
            a.send(b"before", ("serial", 2))
            assert b.receive(TIMEOUT) == (b"before", (relay.b, 1))
            relay.unplug()
            with pytest.raises(OSError):
                _send_until_refused(a)
            assert line.get(timeout=TIMEOUT) is False
            relay.replug()
            assert relay.paths[2] not in relay.paths[:2]
            arrived = threading.Event()

            def keep_sending():
                while not arrived.is_set():
                    try:
                        a.send(b"after", ("serial", 2))
                    except OSError:
                        pass
                    arrived.wait(0.02)

            sender = threading.Thread(target=keep_sending)
            sender.start()
            try:
                got = b.receive(TIMEOUT)
                while got is not None and got[0] != b"after":
                    got = b.receive(TIMEOUT)
            finally:
                arrived.set()
                sender.join()
            assert got == (b"after", (relay.b, 1))
            assert a.downs == b.downs == 1
            assert line.get(timeout=TIMEOUT) is True and line.empty()
        finally:
            a.close()
            b.close()


def _send_until_refused(endpoint, tries=200):
    for _ in range(tries):
        endpoint.send(b"x", ("serial", 2))
        threading.Event().wait(0.01)
