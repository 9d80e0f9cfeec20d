"""The plugin kit: conformance suites and helpers for testing a rosgate plugin.

A plugin's test file runs the suite of its kind by subclassing it (the class name must start
with ``Test`` for pytest to collect it)::

    from rosgate.testing import TransportConformance
    from rosgate_transport_can import CanTransport

    class TestCanConformance(TransportConformance):
        transport = CanTransport               # a Transport subclass, or any factory(options)
        options = {"interface": "virtual"}     # the plugin's table under plugins: (default {})

        @pytest.fixture                        # only for links that do not take 127.0.0.1:port
        def address(self):
            channels = itertools.count(1)
            return lambda: ("vcan0", next(channels))

    class TestCborConformance(CodecConformance):
        codec = CborCodec

    class TestNaclConformance(CipherConformance):
        cipher = NaclCipher                    # keys: generate_key() written to a key_file

What each suite checks (every check uses real sockets, real message classes, real keys):

* :class:`TransportConformance` — datagram links: frames of 1 byte up to ``max_frame`` cross
  byte-exact, and the source a receive reports can be answered; boundaries are kept; an idle
  receive returns ``None``; ``close`` ends a receive blocked in another thread; frames beyond
  ``max_frame`` cross through the core's fragmentation (:class:`rosgate.links.DatagramLink`).
  Stream links: bytes cross both ways byte-exact (up to 1 MiB, both at once); ``max_bytes``
  is honoured; idle receive and accept return ``None``; when the far end closes, receive
  returns ``b""`` and send raises ``OSError``; ``close`` ends a blocked receive; connecting to
  nobody raises ``OSError``; frames cross whole and in order through
  :class:`rosgate.links.StreamLink`, whose ``on_close`` fires when the far end vanishes.
* :class:`CodecConformance` — a round trip of every ROS field kind the installed message
  packages offer (:func:`samples`; raw codecs round-trip the serialized CDR byte for byte), and
  seeded garbage answered by a message of the right type or :class:`rosgate.CodecError`, never
  another exception.
* :class:`CipherConformance` — round trips (empty to 1 MiB) between two instances sharing a
  key; then, for ciphers that authenticate: every flipped bit of the body and of the header,
  another key, every truncation and random bodies are refused with :class:`rosgate.CipherError`;
  two seals of one payload differ. A cipher with ``authenticates = False`` (``none``) skips the
  refusal tests, saying so.
* All three: the plugin is found through its entry point in the group ``rosgate``.

The helpers (:func:`free_port`, :func:`has_ipv6_loopback`, :func:`wait_until_blocked`, :func:`receive_exactly`,
:func:`write_key`, :func:`mutations`, :class:`Frames`) are what plugin tests kept writing for
themselves. rosgate registers this module as a pytest plugin (entry point ``pytest11``), so
pytest rewrites its asserts: a failing check shows the values. Importing it loads nothing from
ROS; the codec suite imports message packages when it runs.
"""

from __future__ import annotations

import functools
import itertools
import random
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator, Mapping

import pytest

from . import envelope
from .cipher import Cipher
from .codec import Codec
from .errors import CipherError, CodecError
from .links import DatagramLink, StreamLink
from .plugins import Plugins
from .transport import Address, StreamConnection, Transport

__all__ = [
    "CipherConformance", "CodecConformance", "Frames", "TransportConformance",
    "free_port", "has_ipv6_loopback", "mutations", "receive_exactly", "sample", "samples", "wait_until_blocked",
    "write_key",
]

TIMEOUT = 5.0  # seconds any single wait in the suites may take before the check fails


# -- helpers ----------------------------------------------------------------------------------

def free_port(host: str = "127.0.0.1") -> int:
    """A port free for both TCP and UDP on ``host`` (IPv4)."""
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
            tcp.bind((host, 0))
            port = tcp.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                try:
                    udp.bind((host, port))
                except OSError:
                    continue
            return port


def has_ipv6_loopback() -> bool:
    """Whether this kernel has ``::1`` (containers often lack it): skip IPv6 tests otherwise."""
    if not socket.has_ipv6:
        return False
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


def wait_until_blocked(native_id: int, timeout: float = 2.0) -> None:
    """Wait until the thread ``native_id`` sleeps in the kernel (a blocking receive), as Linux
    shows it in /proc; skip the test where that cannot be seen."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/self/task/{native_id}/wchan") as f:
                if f.read().strip() not in ("", "0"):
                    return
        except OSError:
            pytest.skip("cannot see where a thread sleeps (/proc/self/task/*/wchan)")
        time.sleep(0.005)
    pytest.fail(f"the thread did not block within {timeout} s")


def receive_exactly(connection: StreamConnection, size: int, timeout: float = TIMEOUT) -> bytes:
    """Read ``size`` bytes from a stream connection, failing the test on timeout or end."""
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


def write_key(path: Path, key: bytes, mode: int = 0o600) -> Path:
    """Write a key file as ``rosgate keygen`` does (the key, a newline, mode 0600)."""
    path.write_bytes(key + b"\n")
    path.chmod(mode)
    return path


def mutations(valid: bytes, rng: random.Random, count: int) -> Iterator[bytes]:
    """``count`` damaged copies of ``valid``: bytes replaced, deleted and inserted, 1 to 3 times."""
    for _ in range(count):
        data = bytearray(valid)
        for _ in range(rng.randrange(1, 4)):
            if not data:
                break
            position = rng.randrange(len(data))
            operation = rng.randrange(3)
            if operation == 0:
                data[position] = rng.randrange(256)
            elif operation == 1:
                del data[position:position + rng.randrange(1, 8)]
            else:
                data[position:position] = rng.randbytes(rng.randrange(1, 8))
        yield bytes(data)


class Frames:
    """Collects what a link hands to ``on_frame`` (and ``on_drop``); wait for a number of them."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []
        self.drops: list[tuple[int | None, str]] = []
        self._cond = threading.Condition()

    def on_frame(self, frame: bytes, link: Any, source: Address) -> None:
        with self._cond:
            self.frames.append(bytes(frame))
            self._cond.notify_all()

    def on_drop(self, topic_id: int | None, reason: str) -> None:
        with self._cond:
            self.drops.append((topic_id, reason))

    def wait_count(self, count: int, timeout: float = TIMEOUT) -> list[bytes]:
        with self._cond:
            self._cond.wait_for(lambda: len(self.frames) >= count, timeout)
            return list(self.frames)


def _frame(size: int, seed: int) -> bytes:
    """Test frames start as rosgate frames do ("RG"), so no whole frame looks like a fragment."""
    return (b"RG" + random.Random(seed).randbytes(size))[:size]


def _in_thread(call: Callable[[], Any]) -> tuple[threading.Thread, threading.Event, list[Any]]:
    """Run ``call`` in a thread; wait until it blocks; return the thread, its end, its result."""
    result: list[Any] = []
    native: list[int] = []
    started, finished = threading.Event(), threading.Event()

    def run() -> None:
        native.append(threading.get_native_id())
        started.set()
        try:
            result.append(call())
        except OSError as exc:
            result.append(exc)
        finished.set()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert started.wait(TIMEOUT)
    wait_until_blocked(native[0])
    return thread, finished, result


def _registered(kind: str, cls: type) -> None:
    registration = Plugins.discover().get(kind, cls.name)
    assert registration is not None, (
        f"no {kind} {cls.name!r} among the installed plugins: is the distribution installed, "
        f"with an entry point in the group 'rosgate'?")
    assert registration.cls is cls


class _Closing:
    """Things to close when the test ends, last opened first."""

    def __init__(self) -> None:
        self.things: list[Any] = []

    def __call__(self, thing: Any) -> Any:
        self.things.append(thing)
        return thing

    def close_all(self) -> None:
        for thing in reversed(self.things):
            try:
                thing.close()
            except OSError:
                pass


# -- transports -------------------------------------------------------------------------------

class TransportConformance:
    """The conformance suite of a transport. Set :attr:`transport` (and :attr:`options`);
    override the ``address`` fixture for links whose addresses are not ``127.0.0.1:port``.
    Tests for the other kind of link (stream or datagram) are skipped, saying so."""

    #: the Transport subclass under test, or a factory taking the options
    transport: ClassVar[Callable[[Mapping[str, Any]], Transport]]
    #: the plugin's options, as under ``plugins:`` in bringup.yaml
    options: ClassVar[Mapping[str, Any]] = {}

    @pytest.fixture
    def address(self) -> Callable[[], Address]:
        """A factory of fresh local addresses, each free to bind or listen on."""
        return lambda: ("127.0.0.1", free_port())

    @pytest.fixture
    def link(self) -> Transport:
        return type(self).transport(dict(self.options))

    @pytest.fixture
    def closing(self) -> Iterator[_Closing]:
        closing = _Closing()
        yield closing
        closing.close_all()

    @staticmethod
    def _kind(link: Transport, stream: bool) -> None:
        if link.stream != stream:
            kind = "a stream" if link.stream else "a datagram"
            pytest.skip(f"{link.name} is {kind} link")

    def test_found_through_its_entry_point(self, link: Transport) -> None:
        _registered("transport", type(link))

    # -- datagram links -----------------------------------------------------------------------

    def _endpoints(self, link: Transport, address: Callable[[], Address], closing: _Closing):
        self._kind(link, stream=False)
        assert link.max_frame > 0, "a datagram link declares its largest frame (max_frame)"
        a_address, b_address = address(), address()
        return closing(link.bind(a_address)), a_address, closing(link.bind(b_address)), b_address

    @pytest.mark.parametrize("size", [lambda m: 1, lambda m: 2, lambda m: m - 1, lambda m: m],
                             ids=["1 byte", "2 bytes", "max_frame-1", "max_frame"])
    def test_datagram_crosses_byte_exact_and_can_be_answered(self, link, address, closing, size):
        a, _, b, b_address = self._endpoints(link, address, closing)
        frame = _frame(size(link.max_frame), seed=size(link.max_frame))
        a.send(frame, b_address)
        got = b.receive(TIMEOUT)
        assert got is not None, "nothing arrived"
        assert got[0] == frame
        # the server role answers a client at the source its datagram reported
        b.send(b"RG answer", got[1])
        answer = a.receive(TIMEOUT)
        assert answer is not None and answer[0] == b"RG answer", \
            f"an answer sent to the reported source {got[1]!r} did not arrive"

    def test_datagram_boundaries_are_kept(self, link, address, closing):
        a, _, b, b_address = self._endpoints(link, address, closing)
        frames = [_frame(size, seed) for seed, size in
                  enumerate([1, link.max_frame, 3, 2, link.max_frame - 1, min(64, link.max_frame)])]
        for frame in frames:
            a.send(frame, b_address)
        got = [b.receive(TIMEOUT) for _ in frames]
        assert None not in got, f"{got.count(None)} of {len(frames)} datagrams never arrived"
        assert sorted(g[0] for g in got) == sorted(frames)

    def test_datagram_idle_receive_returns_none(self, link, address, closing):
        _, _, b, _ = self._endpoints(link, address, closing)
        started = time.monotonic()
        assert b.receive(0.2) is None
        assert 0.15 < time.monotonic() - started < 2.0

    def test_datagram_close_ends_a_blocked_receive(self, link, address, closing):
        _, _, b, _ = self._endpoints(link, address, closing)
        thread, finished, result = _in_thread(lambda: b.receive(30.0))
        b.close()
        assert finished.wait(1.0), "receive still blocked 1 s after close"
        assert result[0] is None or isinstance(result[0], OSError), result
        thread.join()

    def test_datagram_frames_beyond_max_frame_cross_fragmented_by_the_core(
            self, link, address, closing):
        a, _, b, b_address = self._endpoints(link, address, closing)
        m = link.max_frame
        sizes = [1, m, m + 1, 2 * m + 3, min(1 << 20, 200 * m)]
        sent, received = Frames(), Frames()
        tx = closing(DatagramLink(link, a, "conformance-tx", sent.on_frame, sent.on_drop))
        closing(DatagramLink(link, b, "conformance-rx", received.on_frame, received.on_drop))
        frames = [_frame(size, seed) for seed, size in enumerate(sizes)]
        for frame in frames:
            assert tx.send(frame, topic_id=7, to=b_address), f"send of {len(frame)} bytes failed"
        got = received.wait_count(len(frames))
        assert sorted(got) == sorted(frames), \
            f"sent sizes {sizes}, received {sorted(map(len, got))}"
        assert sent.drops == received.drops == []

    # -- stream links -------------------------------------------------------------------------

    def _pair(self, link: Transport, address: Callable[[], Address], closing: _Closing):
        """A connected (client, server) pair of connections."""
        self._kind(link, stream=True)
        where = address()
        listener = closing(link.listen(where))
        client = closing(link.connect(where, TIMEOUT))
        accepted = listener.accept(TIMEOUT)
        assert accepted is not None, "the listener accepted nothing"
        return client, closing(accepted[0])

    def test_stream_bytes_cross_both_ways_byte_exact(self, link, address, closing):
        client, server = self._pair(link, address, closing)
        server.send(b"\x00")
        assert receive_exactly(client, 1) == b"\x00"
        up, down = _frame(1 << 20, 1), _frame(1 << 20, 2)
        errors: list[BaseException] = []

        def send(connection: StreamConnection, data: bytes) -> None:
            try:
                connection.send(data)
            except BaseException as exc:  # reported by the test's thread
                errors.append(exc)

        # both ways at once: a link whose send waits for the far end's receive would deadlock
        senders = [threading.Thread(target=send, args=(client, up), daemon=True),
                   threading.Thread(target=send, args=(server, down), daemon=True)]
        for thread in senders:
            thread.start()
        got_down = receive_exactly(client, len(down))
        got_up = receive_exactly(server, len(up))
        for thread in senders:
            thread.join(TIMEOUT)
        assert errors == []
        assert got_up == up and got_down == down

    def test_stream_receive_honours_max_bytes(self, link, address, closing):
        client, server = self._pair(link, address, closing)
        client.send(b"abcdefgh")
        first = server.receive(3, TIMEOUT)
        assert first and len(first) <= 3
        assert first + receive_exactly(server, 8 - len(first)) == b"abcdefgh"

    def test_stream_idle_receive_and_accept_return_none(self, link, address, closing):
        self._kind(link, stream=True)
        listener = closing(link.listen(address()))
        started = time.monotonic()
        assert listener.accept(0.2) is None
        assert 0.15 < time.monotonic() - started < 2.0
        _, server = self._pair(link, address, closing)
        started = time.monotonic()
        assert server.receive(1024, 0.2) is None
        assert 0.15 < time.monotonic() - started < 2.0

    def test_stream_far_end_closing_ends_receive_and_send(self, link, address, closing):
        client, server = self._pair(link, address, closing)
        client.send(b"last words")
        client.close()
        assert receive_exactly(server, 10) == b"last words"
        assert server.receive(1024, TIMEOUT) == b""
        assert server.receive(1024, TIMEOUT) == b""  # and stays so
        with pytest.raises(OSError):
            for _ in range(100):  # the first writes may still be accepted by the kernel
                server.send(b"x" * 65536)

    def test_stream_close_ends_a_blocked_receive(self, link, address, closing):
        _, server = self._pair(link, address, closing)
        thread, finished, result = _in_thread(lambda: server.receive(1024, 30.0))
        server.close()
        assert finished.wait(1.0), "receive still blocked 1 s after close"
        assert result[0] in (None, b"") or isinstance(result[0], OSError), result
        thread.join()

    def test_stream_connect_to_nobody_raises_oserror(self, link, address):
        self._kind(link, stream=True)
        with pytest.raises(OSError):
            link.connect(address(), TIMEOUT)

    def test_stream_frames_cross_whole_and_in_order_through_the_core(self, link, address, closing):
        client, server = self._pair(link, address, closing)
        sent, received = Frames(), Frames()
        tx = closing(StreamLink(client, "conformance-tx", ("client", 0), sent.on_frame, sent.on_drop))
        closing(StreamLink(server, "conformance-rx", ("server", 0), received.on_frame,
                           received.on_drop))
        frames = [_frame(size, seed) for seed, size in
                  enumerate([1, 2, 100, 65_536, 1 << 20, 3, 4096])]
        for frame in frames:
            assert tx.send(frame, topic_id=7)
        got = received.wait_count(len(frames))
        assert [len(f) for f in got] == [len(f) for f in frames]
        assert got == frames
        assert sent.drops == received.drops == []

    def test_stream_link_reports_the_far_end_vanishing(self, link, address, closing):
        client, server = self._pair(link, address, closing)
        ended = threading.Event()
        received = Frames()
        rx = closing(StreamLink(server, "conformance-rx", ("server", 0), received.on_frame,
                                received.on_drop, on_close=lambda _: ended.set()))
        client.close()
        assert ended.wait(TIMEOUT), "on_close did not fire after the far end closed"
        assert rx.closed.is_set()
        assert rx.send(b"RG too late", topic_id=7) is False
        assert received.drops == [(7, "link_down")]


# -- codecs -----------------------------------------------------------------------------------

@functools.cache
def samples() -> dict[str, Callable[[], Any]]:
    """Name -> a function making a fresh sample message. Together they hold every field kind of
    the installed std_msgs, geometry_msgs, sensor_msgs, builtin_interfaces, rcl_interfaces and
    rmw_dds_common: all integer widths, float32/64, bool, byte, char, string, bounded string,
    fixed arrays (float64[N], uint8[N]), bounded sequences (of messages), unbounded sequences of
    every basic type, of strings and of messages, nested messages, uint8[], time and duration.
    Kinds that no installed message declares are not covered: wstring, and fixed arrays or
    bounded sequences of other element types (rosidl's test_msgs has them; it is not packaged
    here). Values are extremes of their type and exactly representable (float32 fields hold
    float32 values), so equality after a round trip is exact.

    Built on first call: importing the kit imports no ROS package."""
    import math

    import numpy
    from builtin_interfaces.msg import Duration, Time
    from geometry_msgs.msg import PoseWithCovariance, Twist, Vector3
    from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterValue
    from rmw_dds_common.msg import Gid, NodeEntitiesInfo
    from sensor_msgs.msg import (CameraInfo, Image, JointState, NavSatFix, NavSatStatus,
                                 RegionOfInterest)
    from std_msgs import msg as std

    def layout() -> Any:
        return std.MultiArrayLayout(data_offset=1, dim=[
            std.MultiArrayDimension(label="rows", size=2, stride=6),
            std.MultiArrayDimension(label="cols", size=3, stride=3)])

    stamp = Time(sec=-(2**31), nanosec=999_999_999)
    return {
        "Int8": lambda: std.Int8(data=-128), "UInt8": lambda: std.UInt8(data=255),
        "Int16": lambda: std.Int16(data=-(2**15)), "UInt16": lambda: std.UInt16(data=2**16 - 1),
        "Int32": lambda: std.Int32(data=-(2**31)), "UInt32": lambda: std.UInt32(data=2**32 - 1),
        "Int64": lambda: std.Int64(data=-(2**63)), "UInt64": lambda: std.UInt64(data=2**64 - 1),
        "Float32": lambda: std.Float32(data=-(2.0**100)),
        "Float64": lambda: std.Float64(data=math.pi),
        "Float64-inf": lambda: std.Float64(data=-math.inf),
        "Bool": lambda: std.Bool(data=True),
        "Byte": lambda: std.Byte(data=b"\xff"),
        "Char": lambda: std.Char(data=255),
        "String": lambda: std.String(data="héllo, wörld ✓ 日本"),
        "String-empty": lambda: std.String(data=""),
        "Empty": lambda: std.Empty(),
        "Time": lambda: stamp,
        "Duration": lambda: Duration(sec=2**31 - 1, nanosec=1),
        "ByteMultiArray": lambda: std.ByteMultiArray(layout=layout(), data=[b"\x00", b"\xff", b"\x7f"]),
        "UInt8MultiArray": lambda: std.UInt8MultiArray(data=bytes(range(256))),
        "Int8MultiArray": lambda: std.Int8MultiArray(data=[-128, 0, 127]),
        "UInt16MultiArray": lambda: std.UInt16MultiArray(data=[0, 65535]),
        "Int32MultiArray": lambda: std.Int32MultiArray(layout=layout(), data=[-(2**31), 2**31 - 1]),
        "UInt64MultiArray": lambda: std.UInt64MultiArray(data=[0, 2**64 - 1]),
        "Float32MultiArray": lambda: std.Float32MultiArray(layout=layout(),
                                                           data=[0.5, -1.25, 3e38, -math.inf]),
        "Float64MultiArray": lambda: std.Float64MultiArray(data=[1e-300, -1e300, 0.1]),
        "Twist": lambda: Twist(linear=Vector3(x=1.0, y=-2.5, z=1e-9), angular=Vector3(z=0.25)),
        "PoseWithCovariance": lambda: PoseWithCovariance(
            covariance=numpy.arange(36, dtype=numpy.float64) / 7),
        "Image": lambda: Image(header=std.Header(stamp=stamp, frame_id="camera"), height=64,
                               width=256, encoding="mono8", is_bigendian=1, step=256,
                               data=random.Random(1).randbytes(64 * 256)),
        "JointState": lambda: JointState(name=["shoulder", "elbow", ""], position=[0.1, -0.2, 0.0],
                                         velocity=[1.0, 2.0, 3.0], effort=[]),
        "NavSatFix": lambda: NavSatFix(
            status=NavSatStatus(status=-1, service=NavSatStatus.SERVICE_GALILEO),
            latitude=48.8584, longitude=2.2945, altitude=-35.5,
            position_covariance=numpy.linspace(0.0, 8.0, 9), position_covariance_type=2),
        "CameraInfo": lambda: CameraInfo(
            height=480, width=640, distortion_model="plumb_bob", d=[0.1, -0.2, 0.0, 0.0, 0.05],
            k=numpy.linspace(1.0, 9.0, 9), r=numpy.eye(3).ravel(), p=numpy.linspace(0.0, 1.1, 12),
            binning_x=2, roi=RegionOfInterest(x_offset=1, width=10, do_rectify=True)),
        "ParameterValue": lambda: ParameterValue(
            type=9, bool_value=True, integer_value=-(2**63), double_value=0.5, string_value="v",
            byte_array_value=[b"\x01", b"\x00"], bool_array_value=[True, False, True],
            integer_array_value=[2**63 - 1, -1], double_array_value=[1.5],
            string_array_value=["a", "", "ü"]),
        "ParameterDescriptor": lambda: ParameterDescriptor(
            name="gain", floating_point_range=[FloatingPointRange(from_value=-1.0, step=0.5)]),
        "NodeEntitiesInfo": lambda: NodeEntitiesInfo(
            node_namespace="/", node_name="n" * 256,
            reader_gid_seq=[Gid(data=numpy.arange(16, dtype=numpy.uint8))]),
    }


def sample(name: str) -> Any:
    """A fresh sample message of :func:`samples`."""
    return samples()[name]()


class CodecConformance:
    """The conformance suite of a codec. Set :attr:`codec` (and :attr:`options`)."""

    #: the Codec subclass under test
    codec: ClassVar[type[Codec]]
    options: ClassVar[Mapping[str, Any]] = {}
    #: garbage inputs tried per sample message type (random bytes and damaged encodings)
    fuzz_inputs: ClassVar[int] = 400

    def make(self, msg_type: type) -> Codec:
        return self.codec(msg_type, dict(self.options))

    def wire(self, message: Any) -> Any:
        """What ``encode`` takes: the message, or its serialized CDR for a raw codec."""
        if not self.codec.raw:
            return message
        from rclpy.serialization import serialize_message

        return serialize_message(message)

    def test_found_through_its_entry_point(self) -> None:
        _registered("codec", self.codec)

    def pytest_generate_tests(self, metafunc: pytest.Metafunc) -> None:
        if "sample_name" in metafunc.fixturenames:
            metafunc.parametrize("sample_name", list(samples()))

    def test_round_trip(self, sample_name: str) -> None:
        message = sample(sample_name)
        codec = self.make(type(message))
        given = self.wire(message)
        data = codec.encode(given)
        assert isinstance(data, bytes)
        decoded = codec.decode(data)
        if self.codec.raw:
            from rclpy.serialization import deserialize_message

            # byte for byte what was given (serializing twice may differ in padding bytes)
            assert decoded == given
            assert deserialize_message(decoded, type(message)) == message
            return
        assert type(decoded) is type(message)
        assert decoded == message
        assert codec.encode(decoded) == data  # the same message, the same bytes

    def test_authenticated_frames_decode_alike(self) -> None:
        """A codec may trust frames a cipher authenticated (``authenticated = True``); it must
        still decode them to the same message."""
        for name in ("Twist", "Image", "JointState"):
            message = sample(name)
            codec = self.make(type(message))
            codec.authenticated = True
            given = self.wire(message)
            assert codec.decode(codec.encode(given)) == given

    def test_empty_input_is_a_codec_error(self) -> None:
        with pytest.raises(CodecError):
            self.make(type(sample("Twist"))).decode(b"")

    def test_garbage_is_a_codec_error_and_nothing_else(self) -> None:
        """Seeded: random bytes and damaged valid encodings. Each either decodes to a value of
        the right kind or raises CodecError; any other exception fails, showing the input."""
        rng = random.Random(20240601)
        for name in ("Twist", "JointState", "NavSatFix", "ParameterValue", "NodeEntitiesInfo",
                     "Float32MultiArray", "String"):
            message = sample(name)
            codec = self.make(type(message))
            valid = codec.encode(self.wire(message))
            inputs = itertools.chain(
                (rng.randbytes(rng.randrange(64)) for _ in range(self.fuzz_inputs // 2)),
                mutations(valid, rng, self.fuzz_inputs // 2))
            for data in inputs:
                try:
                    result = codec.decode(data)
                except CodecError:
                    continue
                except Exception as exc:  # the point of the test: report, do not propagate
                    pytest.fail(f"{name}: decode({data!r}) raised {type(exc).__name__}: {exc}")
                expected = bytes if self.codec.raw else type(message)
                assert isinstance(result, expected), f"{name}: decode({data!r}) -> {result!r}"


# -- ciphers ----------------------------------------------------------------------------------

HEADER = envelope.pack(0, 7, 0xCAFE, 1, 1_700_000_000_000_000_000)


class CipherConformance:
    """The conformance suite of a cipher. Set :attr:`cipher`; override :meth:`options_for`
    for a cipher whose key does not come from ``key_file``."""

    #: the Cipher subclass under test
    cipher: ClassVar[type[Cipher]]

    def options_for(self, key_file: Path) -> dict[str, Any]:
        """The options naming the key written to ``key_file`` (in the base directory)."""
        return {"key_file": key_file.name}

    @pytest.fixture
    def make_cipher(self, tmp_path: Path) -> Callable[[bytes | None], Cipher]:
        """Build the cipher under ``key`` (None: keyless), as a bridge would from its file."""
        files = itertools.count()

        def make(key: bytes | None) -> Cipher:
            if key is None:
                return self.cipher({}, tmp_path)
            path = write_key(tmp_path / f"{self.cipher.name}-{next(files)}.key", key)
            return self.cipher(self.options_for(path), tmp_path)
        return make

    @pytest.fixture
    def pair(self, make_cipher) -> tuple[Cipher, Cipher]:
        """Two instances under one key: the two sides of a link."""
        key = self.cipher.generate_key()
        return make_cipher(key), make_cipher(key)

    def _authenticating(self) -> None:
        if not self.cipher.authenticates:
            pytest.skip(f"cipher {self.cipher.name!r} does not authenticate (authenticates = False)")

    def test_found_through_its_entry_point(self) -> None:
        _registered("cipher", self.cipher)

    def test_generate_key(self) -> None:
        first = self.cipher.generate_key()
        if first is None:
            return  # keyless
        assert isinstance(first, bytes) and first == first.strip()
        assert self.cipher.generate_key() != first

    @pytest.mark.parametrize("size", [0, 1, 28, 2500, 1 << 20])
    def test_round_trip(self, pair, size: int) -> None:
        sealer, opener = pair
        payload = random.Random(size).randbytes(size)
        body = sealer.seal(HEADER, payload)
        assert isinstance(body, bytes)
        assert opener.open(HEADER, body) == payload
        assert sealer.open(HEADER, body) == payload

    def test_every_flipped_bit_of_the_body_is_refused(self, pair) -> None:
        """Allowed: a flip that opens to the very same payload, all in one byte (an encoding's
        spare bits, as in the padding of Fernet's base64). Never a different payload."""
        self._authenticating()
        sealer, opener = pair
        payload = b"the payload"
        body = sealer.seal(HEADER, payload)
        accepted_at = set()
        for i in range(len(body)):
            for bit in range(8):
                tampered = bytearray(body)
                tampered[i] ^= 1 << bit
                try:
                    opened = opener.open(HEADER, bytes(tampered))
                except CipherError:
                    continue
                assert opened == payload, f"bit {bit} of byte {i} flipped opened to {opened!r}"
                accepted_at.add(i)
        assert len(accepted_at) <= 1, f"flips at bytes {sorted(accepted_at)} were accepted"

    def test_every_flipped_bit_of_the_header_is_refused(self, pair) -> None:
        self._authenticating()
        sealer, opener = pair
        body = sealer.seal(HEADER, b"the payload")
        for i in range(len(HEADER)):
            for bit in range(8):
                other = bytearray(HEADER)
                other[i] ^= 1 << bit
                with pytest.raises(CipherError):
                    opener.open(bytes(other), body)

    def test_another_key_is_refused(self, pair, make_cipher) -> None:
        self._authenticating()
        sealer, _ = pair
        stranger = make_cipher(self.cipher.generate_key())
        with pytest.raises(CipherError):
            stranger.open(HEADER, sealer.seal(HEADER, b"secret"))

    def test_every_truncation_is_refused(self, pair) -> None:
        self._authenticating()
        sealer, opener = pair
        body = sealer.seal(HEADER, b"x" * 40)
        for length in range(len(body)):
            with pytest.raises(CipherError):
                opener.open(HEADER, body[:length])

    def test_garbage_is_a_cipher_error_and_nothing_else(self, pair) -> None:
        self._authenticating()
        _, opener = pair
        rng = random.Random(11)
        for _ in range(500):
            body = rng.randbytes(rng.randrange(300))
            try:
                opener.open(HEADER, body)
            except CipherError:
                continue
            except Exception as exc:  # the point of the test: report, do not propagate
                pytest.fail(f"open({body!r}) raised {type(exc).__name__}: {exc}")
            pytest.fail(f"open accepted random bytes {body!r}")

    def test_two_seals_of_one_payload_differ(self, pair) -> None:
        """A fresh nonce (or IV) per frame: equal payloads must not be seen to be equal."""
        self._authenticating()
        sealer, _ = pair
        assert sealer.seal(HEADER, b"same") != sealer.seal(HEADER, b"same")
