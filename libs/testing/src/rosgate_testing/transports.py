"""The conformance suite of transports: datagram links and stream links, alone and under the
core's links (fragmentation, stream framing)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any, ClassVar

import pytest

from rosgate import Address, DatagramTransport, StreamConnection, StreamTransport, Transport
from rosgate.links.datagram import DatagramLink
from rosgate.options import parse
from rosgate.packetizer import own_packetizer
from rosgate.streamlink.link import StreamLink

from .helpers import (
    TIMEOUT,
    Closing,
    Frames,
    assert_registered,
    frame_of,
    free_port,
    in_thread,
    receive_exactly,
)


class TransportConformance:
    """The conformance suite of a transport. Set :attr:`transport` (and :attr:`options`);
    override the ``address`` fixture for links whose addresses are not ``127.0.0.1:port``.
    The tests of the other kind of link (``test_stream_*`` for a datagram link, and the other
    way round) are left out of a subclass whose :attr:`transport` is a class; with a factory,
    which kind it makes is known only when it runs, and they are skipped, saying so.

    Bus links (CAN) differ from sockets in ways a subclass declares: override the
    ``far_plugin`` fixture when the far end must be another instance of the transport (a node
    that does not hear its own frames); set :attr:`answerable_source` to ``False`` when the
    source a receive reports is not where an answer reaches the sender; set :attr:`ordered`
    when the link promises order, and the suite checks it; set :attr:`padded_length` when
    the link pads frames to certain lengths (CAN FD)."""

    #: the Transport subclass under test, or a factory taking the options
    transport: ClassVar[Callable[[Mapping[str, Any]], Transport]]
    #: the plugin's options, as under ``plugins:`` in bringup.yaml
    options: ClassVar[Mapping[str, Any]] = {}
    #: datagram links: whether the source a receive reports is the sender's address, so that
    #: an answer sent there reaches it (UDP). ``False`` (a bus, whose receive reports the
    #: receiving port): the suite answers at the sender's known address instead, still
    #: checking that the answer arrives byte-exact
    answerable_source: ClassVar[bool] = True
    #: datagram links: whether frames from one sender arrive in the order sent (a CAN bus per
    #: arbitration id). ``True`` makes the suite check the order, not only the contents
    ordered: ClassVar[bool] = False
    #: datagram links whose frames travel padded (CAN FD carries 0-8, 12, 16, 20, 24, 32, 48
    #: or 64 data bytes): the length a frame of ``n`` bytes arrives with, zeros added. The
    #: suite then expects exactly those zeros after the frame; the core's fragmentation must
    #: still deliver frames at their own length. ``None``: every frame keeps its length
    padded_length: ClassVar[Callable[[int], int] | None] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        transport = cls.__dict__.get("transport")
        if isinstance(transport, type) and issubclass(transport, Transport):
            other = "test_datagram_" if issubclass(transport, StreamTransport) else "test_stream_"
            for name in dir(TransportConformance):
                if name.startswith(other):
                    setattr(cls, name, None)  # pytest collects functions only

    @pytest.fixture
    def address(self) -> Callable[[], Address]:
        """A factory of fresh local addresses, each free to bind or listen on."""
        return lambda: ("127.0.0.1", free_port())

    @pytest.fixture
    def plugin(self) -> Transport:
        """The transport under test, made from :attr:`options` as the core makes it (a factory
        gets the options as a dict)."""
        make = type(self).transport
        return make(parse(make, self.options) if isinstance(make, type) else dict(self.options))

    @pytest.fixture
    def far_plugin(self, plugin: Transport) -> Transport:
        """The transport the far end binds (datagram) or listens (stream) with. The same
        instance by default, as two sockets of one process talk through one UDP or TCP stack;
        a bus link overrides it with another instance on the same bus, as a second node."""
        return plugin

    @pytest.fixture
    def closing(self) -> Iterator[Closing]:
        closing = Closing()
        yield closing
        closing.close_all()

    @staticmethod
    def _kind(plugin: Transport, stream: bool) -> None:
        if isinstance(plugin, StreamTransport) != stream:
            kind = "a stream" if isinstance(plugin, StreamTransport) else "a datagram"
            pytest.skip(f"{plugin.name} is {kind} link")

    def test_found_through_its_entry_point(self, plugin: Transport) -> None:
        assert_registered("transport", type(plugin))

    # -- datagram links -----------------------------------------------------------------------

    def _endpoints(self, plugin: Transport, far_plugin: Transport,
                   address: Callable[[], Address], closing: Closing):
        """(a, a's address, b, b's address): ``a`` bound with ``plugin``, ``b`` with
        ``far_plugin``."""
        self._kind(plugin, stream=False)
        assert isinstance(plugin, DatagramTransport), "a datagram link subclasses DatagramTransport"
        assert isinstance(far_plugin, DatagramTransport), "far_plugin must make a datagram link too"
        assert plugin.max_frame > 0, "a datagram link declares its largest frame (max_frame)"
        assert far_plugin.max_frame == plugin.max_frame, \
            "the far_plugin fixture must make the same link (its max_frame differs)"
        a_address, b_address = address(), address()
        assert a_address != b_address, "the address fixture must give a fresh address each call"
        a, b = closing(plugin.bind(a_address)), closing(far_plugin.bind(b_address))
        return a, a_address, b, b_address

    def _as_received(self, frame: bytes) -> bytes:
        """What a bare datagram of ``frame`` arrives as: itself, or itself padded."""
        pad = type(self).padded_length  # read off the class: a plain function is not bound
        if pad is None:
            return frame
        padded = pad(len(frame))
        assert padded >= len(frame), f"padded_length({len(frame)}) = {padded} is shorter"
        return frame + bytes(padded - len(frame))

    @pytest.mark.parametrize("size", [lambda m: 1, lambda m: 2, lambda m: m - 1, lambda m: m],
                             ids=["1 byte", "2 bytes", "max_frame-1", "max_frame"])
    def test_datagram_crosses_byte_exact_and_can_be_answered(
            self, plugin, far_plugin, address, closing, size):
        a, a_address, b, b_address = self._endpoints(plugin, far_plugin, address, closing)
        frame = frame_of(size(plugin.max_frame), seed=size(plugin.max_frame))
        a.send(frame, b_address)
        got = b.receive(TIMEOUT)
        assert got is not None, "nothing arrived"
        assert got[0] == self._as_received(frame)
        hash(got[1])  # the core keys reassembly on the source: it must be hashable
        # the server role answers a client at the source its datagram reported; on a bus the
        # source names the receiving port, and an answer goes to the sender's known port
        to = got[1] if self.answerable_source else a_address
        answer_frame = frame_of(min(9, plugin.max_frame), seed=99)  # fits classic CAN too
        b.send(answer_frame, to)
        answer = a.receive(TIMEOUT)
        assert answer is not None, (
            f"an answer sent to the reported source {to!r} did not arrive"
            if self.answerable_source else f"an answer sent to {to!r} did not arrive")
        assert answer[0] == self._as_received(answer_frame)

    def test_datagram_boundaries_are_kept(self, plugin, far_plugin, address, closing):
        a, _, b, b_address = self._endpoints(plugin, far_plugin, address, closing)
        frames = [frame_of(size, seed) for seed, size in
                  enumerate([1, plugin.max_frame, 3, 2, plugin.max_frame - 1,
                             min(64, plugin.max_frame)])]
        for frame in frames:
            a.send(frame, b_address)
        got = [b.receive(TIMEOUT) for _ in frames]
        assert None not in got, f"{got.count(None)} of {len(frames)} datagrams never arrived"
        expected = [self._as_received(frame) for frame in frames]
        if self.ordered:
            assert [g[0] for g in got] == expected
        else:
            assert sorted(g[0] for g in got) == sorted(expected)

    def test_datagram_idle_receive_returns_none(self, plugin, far_plugin, address, closing):
        _, _, b, _ = self._endpoints(plugin, far_plugin, address, closing)
        started = time.monotonic()
        assert b.receive(0.2) is None
        assert 0.15 < time.monotonic() - started < 2.0

    def test_datagram_close_ends_a_blocked_receive(self, plugin, far_plugin, address, closing):
        _, _, b, _ = self._endpoints(plugin, far_plugin, address, closing)
        thread, finished, result = in_thread(lambda: b.receive(30.0))
        b.close()
        assert finished.wait(1.0), "receive still blocked 1 s after close"
        assert result[0] is None or isinstance(result[0], OSError), result
        thread.join()

    def test_datagram_receive_into_if_offered(self, plugin, far_plugin, address, closing):
        """The optional fast path (:class:`rosgate.FastDatagramEndpoint`): a frame written into
        the core's buffer, its length, an answerable source and when it arrived (0, or a time
        on time.time_ns()'s clock, not in the future); None when idle."""
        a, a_address, b, b_address = self._endpoints(plugin, far_plugin, address, closing)
        if not hasattr(b, "receive_into"):
            pytest.skip(f"{plugin.name} does not offer receive_into (optional)")
        buffer = memoryview(bytearray(max(plugin.max_frame, 65_535) + 1))
        buffer[:] = b"\xee" * len(buffer)
        frames = [frame_of(size, seed) for seed, size in enumerate([plugin.max_frame, 1, 3])]
        for frame in frames:
            sent = time.time_ns()
            a.send(frame, b_address)
            got = b.receive_into(buffer, TIMEOUT)
            assert got is not None, "nothing arrived"
            size, source, arrived = got
            assert bytes(buffer[:size]) == self._as_received(frame)
            hash(source)
            assert arrived == 0 or sent - 1_000_000_000 < arrived <= time.time_ns(), \
                "arrival times are time.time_ns() nanoseconds, or 0"
        answer = frame_of(min(9, plugin.max_frame), seed=7)
        b.send(answer, source if self.answerable_source else a_address)
        got = a.receive(TIMEOUT)
        assert got is not None and got[0] == self._as_received(answer)
        started = time.monotonic()
        assert b.receive_into(buffer, 0.2) is None
        assert 0.15 < time.monotonic() - started < 2.0

    def test_datagram_send_parts_if_offered(self, plugin, far_plugin, address, closing):
        """The optional fast path: the parts (bytes and views) leave as one frame, in order."""
        a, _, b, b_address = self._endpoints(plugin, far_plugin, address, closing)
        if not hasattr(a, "send_parts"):
            pytest.skip(f"{plugin.name} does not offer send_parts (optional)")
        whole = frame_of(plugin.max_frame, seed=11)
        cut = min(14, plugin.max_frame // 2)
        for parts in ([whole[:cut], memoryview(whole)[cut:]], [whole], [b"", whole, b""]):
            a.send_parts(parts, b_address)
            got = b.receive(TIMEOUT)
            assert got is not None, "nothing arrived"
            assert got[0] == self._as_received(whole)

    def test_datagram_frames_beyond_max_frame_cross_fragmented_by_the_core(
            self, plugin, far_plugin, address, closing):
        a, _, b, b_address = self._endpoints(plugin, far_plugin, address, closing)
        m = plugin.max_frame
        # DatagramLink picks its own packetizer by max_frame: 14-byte fragment headers, or below
        # SMALL_FRAME (CAN's 8 and 64) compact pieces, whose length field grows a byte at
        # 128 and 16384 and whose 7-bit piece counter wraps past 128 pieces
        sizes = [1, m, m + 1, 2 * m + 3, 127, 128, 16_384, min(1 << 20, 200 * m)]
        sent, received = Frames(), Frames()
        tx = closing(DatagramLink(plugin, a, "conformance-tx", sent.on_frame, sent.on_lost))
        rx = closing(DatagramLink(far_plugin, b, "conformance-rx", received.on_frame,
                                  received.on_lost))
        assert tx.own.name == rx.own.name == own_packetizer(m)
        frames = [frame_of(size, seed) for seed, size in enumerate(sizes)]
        for frame in frames:
            assert tx.send(frame, sent.sender(7), to=b_address), (
                f"send of {len(frame)} bytes failed")
        got = received.wait_count(len(frames))
        if self.ordered:
            assert [len(f) for f in got] == sizes
            assert got == frames
        else:
            assert sorted(got) == sorted(frames), \
                f"sent sizes {sizes}, received {sorted(map(len, got))}"
        assert sent.drops == received.drops == []

    # -- stream links -------------------------------------------------------------------------

    def _pair(self, plugin: Transport, far_plugin: Transport, address: Callable[[], Address],
              closing: Closing):
        """A connected (client, server) pair of connections: the client connects with
        ``plugin``, the server listens with ``far_plugin``."""
        self._kind(plugin, stream=True)
        assert isinstance(plugin, StreamTransport)  # for the type checker: _kind skipped others
        assert isinstance(far_plugin, StreamTransport), "far_plugin must make a stream link too"
        where = address()
        listener = closing(far_plugin.listen(where))
        client = closing(plugin.connect(where, TIMEOUT))
        accepted = listener.accept(TIMEOUT)
        assert accepted is not None, "the listener accepted nothing"
        return client, closing(accepted[0])

    def test_stream_bytes_cross_both_ways_byte_exact(self, plugin, far_plugin, address, closing):
        client, server = self._pair(plugin, far_plugin, address, closing)
        server.send(b"\x00")
        assert receive_exactly(client, 1) == b"\x00"
        up, down = frame_of(1 << 20, 1), frame_of(1 << 20, 2)
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

    def test_stream_receive_honours_max_bytes(self, plugin, far_plugin, address, closing):
        client, server = self._pair(plugin, far_plugin, address, closing)
        client.send(b"abcdefgh")
        first = server.receive(3, TIMEOUT)
        assert first and len(first) <= 3
        assert first + receive_exactly(server, 8 - len(first)) == b"abcdefgh"

    def test_stream_idle_receive_and_accept_return_none(self, plugin, far_plugin, address, closing):
        self._kind(plugin, stream=True)
        listener = closing(plugin.listen(address()))
        started = time.monotonic()
        assert listener.accept(0.2) is None
        assert 0.15 < time.monotonic() - started < 2.0
        _, server = self._pair(plugin, far_plugin, address, closing)
        started = time.monotonic()
        assert server.receive(1024, 0.2) is None
        assert 0.15 < time.monotonic() - started < 2.0

    def test_stream_far_end_closing_ends_receive_and_send(
            self, plugin, far_plugin, address, closing):
        client, server = self._pair(plugin, far_plugin, address, closing)
        client.send(b"last words")
        client.close()
        assert receive_exactly(server, 10) == b"last words"
        assert server.receive(1024, TIMEOUT) == b""
        assert server.receive(1024, TIMEOUT) == b""  # and stays so
        with pytest.raises(OSError):
            for _ in range(100):  # the first writes may still be accepted by the kernel
                server.send(b"x" * 65536)

    def test_stream_close_ends_a_blocked_receive(self, plugin, far_plugin, address, closing):
        _, server = self._pair(plugin, far_plugin, address, closing)
        thread, finished, result = in_thread(lambda: server.receive(1024, 30.0))
        server.close()
        assert finished.wait(1.0), "receive still blocked 1 s after close"
        assert result[0] in (None, b"") or isinstance(result[0], OSError), result
        thread.join()

    def test_stream_receive_into_if_offered(self, plugin, far_plugin, address, closing):
        """The optional fast path (:class:`rosgate.FastStreamConnection`): bytes written into
        the core's buffer, at most its length; None when idle; 0 once the far end closed."""
        client, server = self._pair(plugin, far_plugin, address, closing)
        if not hasattr(server, "receive_into"):
            pytest.skip(f"{plugin.name} does not offer receive_into on streams (optional)")
        data = frame_of(100_000, 3)
        client.send(data)
        buffer, got = memoryview(bytearray(4096)), bytearray()
        while len(got) < len(data):
            n = server.receive_into(buffer, TIMEOUT)
            assert n, f"only {len(got)} of {len(data)} bytes came"
            assert n <= len(buffer)
            got += buffer[:n]
        assert got == data
        assert server.receive_into(buffer, 0.2) is None
        client.close()
        assert server.receive_into(buffer, TIMEOUT) == 0

    def test_stream_send_nowait_if_offered(self, plugin, far_plugin, address, closing):
        """The optional fast path: what goes without waiting is written and counted, never more
        than was given, and the rest can follow with send."""
        client, server = self._pair(plugin, far_plugin, address, closing)
        if not hasattr(client, "send_nowait"):
            pytest.skip(f"{plugin.name} does not offer send_nowait (optional)")
        data = frame_of(4 << 20, 4)  # more than a socket buffer takes at once
        written = client.send_nowait(data)
        assert 0 <= written <= len(data)
        senders = [threading.Thread(target=client.send, args=(data[written:],), daemon=True)]
        senders[0].start()
        assert receive_exactly(server, len(data), TIMEOUT * 4) == data
        senders[0].join(TIMEOUT)

    def test_stream_connect_to_nobody_raises_oserror(self, plugin, address):
        self._kind(plugin, stream=True)
        with pytest.raises(OSError):
            plugin.connect(address(), TIMEOUT)

    def test_stream_frames_cross_whole_and_in_order_through_the_core(
            self, plugin, far_plugin, address, closing):
        client, server = self._pair(plugin, far_plugin, address, closing)
        sent, received = Frames(), Frames()
        tx = closing(StreamLink(client, "conformance-tx", ("client", 0), sent.on_frame,
                                sent.on_lost))
        closing(StreamLink(server, "conformance-rx", ("server", 0), received.on_frame,
                           received.on_lost))
        frames = [frame_of(size, seed) for seed, size in
                  enumerate([1, 2, 100, 65_536, 1 << 20, 3, 4096])]
        for frame in frames:
            assert tx.send(frame, sent.sender(7))
        got = received.wait_count(len(frames))
        assert [len(f) for f in got] == [len(f) for f in frames]
        assert got == frames
        assert sent.drops == received.drops == []

    def test_stream_link_reports_the_far_end_vanishing(self, plugin, far_plugin, address, closing):
        client, server = self._pair(plugin, far_plugin, address, closing)
        ended = threading.Event()
        received = Frames()
        rx = closing(StreamLink(server, "conformance-rx", ("server", 0), received.on_frame,
                                received.on_lost, on_close=lambda _: ended.set()))
        client.close()
        assert ended.wait(TIMEOUT), "on_close did not fire after the far end closed"
        assert rx.closed.is_set()
        assert rx.send(b"RG too late", received.sender(7)) is False
        assert received.drops == [(7, "link_down")]
