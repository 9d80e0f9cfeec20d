"""The link emulator: what crosses it, what it loses, how fast and how late (real sockets on
127.0.0.1, seeded, waiting on counters and arrivals with timeouts)."""

from __future__ import annotations

import dataclasses
import json
import math
import random
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import pytest
from rosgate_emulator import (
    WIFI,
    NetnsPair,
    Profile,
    TcpRelay,
    UdpRelay,
    ip_fragments,
    udp_wire_bytes,
)

TIMEOUT = 10.0
BUFFER = 8 << 20


SO_TIMESTAMPNS = 35   # Linux: the kernel stamps each datagram's arrival (CLOCK_REALTIME)
TIMESPEC = struct.Struct("@qq")


class Sink:
    """Receives on a UDP socket in a thread: (arrival time, bytes, source) per datagram, the
    time stamped by the kernel as the datagram reached the socket (``time.time()`` clock), so
    a busy machine delaying this thread does not skew rates and latencies; ``reply`` (if
    given) answers each datagram to its source."""

    def __init__(self, sock: socket.socket, reply=None):
        self.sock, self.reply = sock, reply
        self.items: list[tuple[float, bytes, tuple]] = []
        self.changed = threading.Condition()
        self.stopping = threading.Event()
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.settimeout(0.05)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.stopping.is_set():
            try:
                data, ancillary, _, source = self.sock.recvmsg(65535, 64)
            except TimeoutError:
                continue
            except OSError:
                return
            now = time.time()
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    seconds, nanoseconds = TIMESPEC.unpack(value[:TIMESPEC.size])
                    now = seconds + nanoseconds / 1e9
            if self.reply is not None:
                self.sock.sendto(self.reply(data), source)
            with self.changed:
                self.items.append((now, data, source))
                self.changed.notify_all()

    def wait_for(self, count: int, timeout: float = TIMEOUT) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: len(self.items) >= count, timeout)

    @property
    def data(self) -> list[bytes]:
        with self.changed:
            return [d for _, d, _ in self.items]

    def close(self):
        self.stopping.set()
        self.thread.join(TIMEOUT)


@pytest.fixture
def udp():
    """A factory of UDP sockets bound on 127.0.0.1 with large buffers, closed afterwards."""
    made: list[socket.socket] = []
    sinks: list[Sink] = []

    def make(sink: bool = False, reply=None):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        made.append(sock)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BUFFER)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, BUFFER)
        sock.bind(("127.0.0.1", 0))
        if sink:
            sinks.append(Sink(sock, reply))
            return sock, sinks[-1]
        return sock

    yield make
    for s in sinks:
        s.close()
    for sock in made:
        sock.close()


def numbered(i: int, size: int) -> bytes:
    """A datagram that says which one it is, padded with bytes that depend on it."""
    head = i.to_bytes(4, "big")
    return head + random.Random(i).randbytes(size - 4)


def send_all(relay: UdpRelay, sock: socket.socket, datagrams, batch: int = 500):
    """Send in batches, each once the relay has read the one before (no kernel drops)."""
    sent = relay.up.datagrams_in
    for start in range(0, len(datagrams), batch):
        for d in datagrams[start:start + batch]:
            sock.sendto(d, relay.address)
        sent += len(datagrams[start:start + batch])
        assert relay.wait_until(lambda up, down: up.datagrams_in >= sent,  # noqa: B023 - polled here
                                TIMEOUT)


def settled(up) -> bool:
    return up.datagrams_delivered + sum(up.dropped.values()) >= up.datagrams_in


# --- arithmetic and profiles ------------------------------------------------------------

def test_fragment_arithmetic_is_ipv4s():
    assert ip_fragments(0) == 1
    assert ip_fragments(1472) == 1                 # 1472 + 8 + 20 = 1500
    assert ip_fragments(1473) == 2
    assert ip_fragments(2952) == 2                 # 2960 = 2 * 1480
    assert ip_fragments(2953) == 3
    assert ip_fragments(4000) == 3                 # 4008 = 1480 + 1480 + 1048
    assert ip_fragments(65507) == 45               # 65515 / 1480 = 44.3
    assert ip_fragments(1000, mtu=576) == 2        # fragments of 552 (a multiple of 8)
    assert ip_fragments(1000, mtu=579) == 2        # 559 is rounded down to 552
    assert udp_wire_bytes(4000) == 4000 + 8 + 3 * 20
    assert udp_wire_bytes(100) == 128
    with pytest.raises(ValueError):
        ip_fragments(65508)


def test_profiles_validate_and_derive_the_rto():
    assert (WIFI.rate, WIFI.delay, WIFI.jitter, WIFI.loss, WIFI.mtu) == (20e6, 0.01, 0.002,
                                                                          0.01, 1500)
    assert WIFI.rto_s == 0.2                       # RTT 24 ms: Linux's minimum RTO rules
    assert Profile(delay=0.1).rto_s == pytest.approx(0.4)   # 2 * RTT
    assert Profile(rto=0.05).rto_s == 0.05
    assert WIFI.mss == 1460
    for bad in ({"rate": 0}, {"loss": 1.0}, {"loss": -0.1}, {"jitter": -1}, {"mtu": 60},
                {"queue": 0}, {"burst": -1}, {"rto": 0}):
        with pytest.raises(ValueError):
            Profile(**bad)
    with pytest.raises(dataclasses.FrozenInstanceError):
        WIFI.loss = 0.5  # type: ignore[misc]


# --- UDP --------------------------------------------------------------------------------

def test_datagrams_cross_byte_exact_both_ways_and_replies_reach_the_client(udp):
    target, echo = udp(sink=True, reply=lambda d: b"re:" + d[::-1][:65504])
    client = udp()
    profile = Profile(rate=50e6, delay=0.005, jitter=0.002, seed=1)
    with UdpRelay(profile, target.getsockname()) as relay:
        sizes = [1, 100, 1472, 1473, 4000, 65507]
        for i, size in enumerate(sizes):
            data = numbered(i, max(size, 4))[:size]
            client.settimeout(TIMEOUT)
            client.sendto(data, relay.address)
            reply, source = client.recvfrom(65535)
            assert source == relay.address
            assert echo.wait_for(i + 1)
            assert echo.data[i] == data
            assert reply == b"re:" + data[::-1][:65504]
        # a scheduler counts a datagram just after sending it: wait for the count
        assert relay.wait_until(lambda up, down: up.datagrams_delivered == len(sizes)
                                and down.datagrams_delivered == len(sizes), TIMEOUT)
        up, down = relay.up, relay.down
        assert up.datagrams_in == up.datagrams_delivered == len(sizes)
        assert up.bytes_delivered == sum(sizes)
        assert down.datagrams_delivered == len(sizes)
        assert up.dropped == down.dropped == {"loss": 0, "queue_full": 0}


def test_loss_delivers_a_binomial_fraction(udp):
    target, sink = udp(sink=True)
    client = udp()
    n, p = 5000, 0.1
    datagrams = [numbered(i, 1000) for i in range(n)]
    with UdpRelay(Profile(loss=p, seed=2), target.getsockname()) as relay:
        send_all(relay, client, datagrams)
        assert relay.wait_until(lambda up, down: settled(up), TIMEOUT)
        up = relay.up
        assert sink.wait_for(up.datagrams_delivered)
        assert up.dropped["loss"] + up.datagrams_delivered == n
    bound = 4.5 * math.sqrt(n * p * (1 - p))              # 4.5 sigma: ~1 in 150,000
    assert abs(up.datagrams_delivered - n * (1 - p)) <= bound
    received = sink.data
    assert len(received) == up.datagrams_delivered
    assert all(d == datagrams[int.from_bytes(d[:4], "big")] for d in received)


def test_a_fragmented_datagram_is_lost_when_any_fragment_is(udp):
    target, sink = udp(sink=True)
    client = udp()
    n, p = 1500, 0.1
    assert ip_fragments(4000) == 3
    datagrams = [numbered(i, 4000) for i in range(n)]
    with UdpRelay(Profile(loss=p, seed=3), target.getsockname()) as relay:
        send_all(relay, client, datagrams, batch=250)
        assert relay.wait_until(lambda up, down: settled(up), TIMEOUT)
        up = relay.up
        assert sink.wait_for(up.datagrams_delivered)
    q = 1 - (1 - p) ** 3                                  # 0.271
    assert abs(up.dropped["loss"] - n * q) <= 4.5 * math.sqrt(n * q * (1 - q))
    assert len(sink.data) == up.datagrams_delivered


def test_the_same_seed_loses_the_same_datagrams(udp):
    def delivered(seed) -> list[int]:
        target, sink = udp(sink=True)
        client = udp()
        with UdpRelay(Profile(loss=0.3, jitter=0.001, seed=seed), target.getsockname()) as relay:
            send_all(relay, client, [numbered(i, 200) for i in range(400)])
            assert relay.wait_until(lambda up, down: settled(up), TIMEOUT)
            assert sink.wait_for(relay.up.datagrams_delivered)
        return [int.from_bytes(d[:4], "big") for d in sink.data]

    first = delivered(7)
    assert 200 < len(first) < 360
    assert delivered(7) == first
    assert delivered(8) != first


def test_the_rate_caps_what_is_delivered(udp):
    target, sink = udp(sink=True)
    client = udp()
    rate, size, seconds = 4e6, 1000, 2.0
    wire = udp_wire_bytes(size)
    profile = Profile(rate=rate, queue=100_000, seed=4)   # 200 ms: absorbs a stalled sender
    per_tick = 10
    interval = per_tick * wire * 8 / (2 * rate)           # offers twice the rate
    with UdpRelay(profile, target.getsockname()) as relay:
        start = time.monotonic()
        tick, i = start, 0
        while tick - start < seconds:
            for _ in range(per_tick):
                client.sendto(numbered(i, size), relay.address)
                i += 1
            tick += interval
            time.sleep(max(0.0, tick - time.monotonic()))     # pacing the sender
        assert relay.wait_until(lambda up, down: up.datagrams_in >= i and settled(up), TIMEOUT)
        up = relay.up
        assert sink.wait_for(up.datagrams_delivered)
    times = [t for t, _, _ in sink.items]
    measured = (len(times) - 1) * wire * 8 / (times[-1] - times[0])
    assert measured == pytest.approx(rate, rel=0.10)
    assert up.dropped["queue_full"] > 0.2 * i             # ~40 %: half, less what queued
    assert up.queue_max <= profile.queue


def test_a_burst_beyond_the_queue_is_tail_dropped(udp):
    target, sink = udp(sink=True)
    client = udp()
    profile = Profile(rate=1e6, queue=10_000, seed=5)     # 1,028 wire bytes take 8 ms each
    datagrams = [numbered(i, 1000) for i in range(50)]
    with UdpRelay(profile, target.getsockname()) as relay:
        for d in datagrams:
            client.sendto(d, relay.address)
        assert relay.wait_until(lambda up, down: up.datagrams_in == 50 and settled(up), TIMEOUT)
        up = relay.up
        assert sink.wait_for(up.datagrams_delivered)
    assert up.dropped["queue_full"] >= 30
    assert up.dropped["queue_full"] + up.datagrams_delivered == 50
    assert 9 * 1028 <= up.queue_max <= profile.queue
    received = [int.from_bytes(d[:4], "big") for d in sink.data]
    assert received == sorted(received)                   # what got in left in order
    assert received[:9] == list(range(9))                 # the head of the burst got in
    assert all(d == datagrams[int.from_bytes(d[:4], "big")] for d in sink.data)


def latencies(udp, profile: Profile, count: int = 200,
              spacing: float = 0.0) -> tuple[list[float], list[int], float]:
    """Send ``count`` datagrams ``spacing`` s apart; their one-way latencies, arrival order,
    and the relay's late_max."""
    target, sink = udp(sink=True)
    client = udp()
    sent: dict[int, float] = {}
    with UdpRelay(profile, target.getsockname()) as relay:
        start = time.monotonic()
        for i in range(count):
            time.sleep(max(0.0, start + i * spacing - time.monotonic()))   # pacing the sender
            sent[i] = time.time()
            client.sendto(numbered(i, 100), relay.address)
        assert sink.wait_for(count)
        late = relay.up.late_max
    order = [int.from_bytes(d[:4], "big") for _, d, _ in sink.items]
    return [t - sent[int.from_bytes(d[:4], "big")] for t, d, _ in sink.items], order, late


def test_delay_is_the_least_latency_and_jitter_adds_uniformly(udp):
    delay, jitter = 0.03, 0.01
    profile = Profile(delay=delay, jitter=jitter, reorder=True, seed=6)
    observed, order, late = latencies(udp, profile, spacing=0.001)
    assert min(observed) >= delay
    mean = sum(observed) / len(observed)
    # expected: delay + jitter / 2; a busy machine makes the relay late, and says by how much
    assert delay + 0.4 * jitter <= mean <= delay + jitter + 0.003 + late
    assert order != sorted(order)                          # reorder=True lets jitter reorder


def test_without_reorder_jitter_keeps_the_order(udp):
    delay, jitter = 0.01, 0.02
    observed, order, _ = latencies(udp, Profile(delay=delay, jitter=jitter, seed=6))
    assert order == list(range(200))
    assert min(observed) >= delay


def test_the_target_answers_to_the_source_address_and_early_answers_are_dropped(udp):
    target, echo = udp(sink=True, reply=lambda d: d.upper())
    source = udp()
    fixed = source.getsockname()
    source.close()                                         # a free port for the relay to take
    with UdpRelay(Profile(), target.getsockname(), source=fixed) as relay:
        assert relay.source_address == fixed
        target.sendto(b"too early", fixed)                 # no client has sent yet
        assert relay.wait_until(lambda up, down: down.dropped.get("no_client") == 1, TIMEOUT)
        client = udp()
        client.settimeout(TIMEOUT)
        client.sendto(b"hello", relay.address)
        assert client.recvfrom(100) == (b"HELLO", relay.address)
        assert echo.wait_for(1) and echo.items[0][2] == fixed  # seen from there


# --- TCP --------------------------------------------------------------------------------

@pytest.fixture
def tcp_target():
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    listener.settimeout(TIMEOUT)
    yield listener
    listener.close()


def receive_all(sock: socket.socket, out: bytearray, times: list[float]):
    sock.settimeout(TIMEOUT * 2)
    while chunk := sock.recv(1 << 16):
        if not times:
            times.append(time.monotonic())
        out += chunk
    times.append(time.monotonic())


def send_and_end(sock: socket.socket, data: bytes):
    sock.sendall(data)
    sock.shutdown(socket.SHUT_WR)


def test_tcp_crosses_intact_and_in_order_through_loss_at_the_rate(tcp_target):
    rate = 8e6
    profile = Profile(rate=rate, delay=0.005, jitter=0.001, loss=0.05, rto=0.05, seed=9)
    up_data = random.Random(1).randbytes(2 << 20)
    down_data = random.Random(2).randbytes(256 << 10)
    with TcpRelay(profile, tcp_target.getsockname()) as relay:
        client = socket.create_connection(relay.address, timeout=TIMEOUT)
        server, _ = tcp_target.accept()
        got_up, got_down = bytearray(), bytearray()
        up_times: list[float] = []
        readers = [threading.Thread(target=receive_all, args=(server, got_up, up_times)),
                   threading.Thread(target=receive_all, args=(client, got_down, []))]
        for r in readers:
            r.start()
        writers = [threading.Thread(target=send_and_end, args=(s, d))
                   for s, d in ((client, up_data), (server, down_data))]
        for w in writers:
            w.start()
        for t in readers + writers:
            t.join(TIMEOUT * 2)
        assert relay.wait_until(lambda up, down: up.bytes_delivered == len(up_data)
                                and down.bytes_delivered == len(down_data), TIMEOUT)
        up, down = relay.up, relay.down
        client.close()
        server.close()
    assert bytes(got_up) == up_data
    assert bytes(got_down) == down_data
    assert up.retransmitted > 0 and down.retransmitted > 0
    assert up.bytes_in == up.bytes_delivered == len(up_data)
    assert down.bytes_in == down.bytes_delivered == len(down_data)
    elapsed = up_times[-1] - up_times[0]
    throughput = len(up_data) * 8 / elapsed
    # the model's goodput: headers take 40 of every 1,500 bytes, each retransmission a slot
    goodput = rate * profile.mss / profile.mtu * up.segments_in / (up.segments_in
                                                                   + up.retransmitted)
    assert throughput == pytest.approx(goodput, rel=0.10)   # goodput is ~0.925 of the rate
    assert 0.8 * rate < throughput < rate


def test_tcp_backpressure_bounds_the_queue_and_drops_nothing(tcp_target):
    profile = Profile(rate=4e6, queue=20_000, seed=10)
    data = random.Random(3).randbytes(400_000)
    with TcpRelay(profile, tcp_target.getsockname()) as relay:
        client = socket.create_connection(relay.address, timeout=TIMEOUT)
        server, _ = tcp_target.accept()
        got, times = bytearray(), []
        reader = threading.Thread(target=receive_all, args=(server, got, times))
        reader.start()
        client.sendall(data)
        client.shutdown(socket.SHUT_WR)
        reader.join(TIMEOUT)
        up = relay.up
        client.close()
        server.close()
    assert bytes(got) == data
    assert 0 < up.queue_max <= profile.queue
    assert len(data) * 8 / (times[-1] - times[0]) < 4e6 * 1.02


def test_a_lost_segment_holds_the_stream_for_the_rto(tcp_target):
    profile = Profile(delay=0.001, loss=0.3, seed=11)      # default RTO: 200 ms
    assert profile.rto_s == 0.2
    data = random.Random(4).randbytes(20 * profile.mss)
    with TcpRelay(profile, tcp_target.getsockname()) as relay:
        client = socket.create_connection(relay.address, timeout=TIMEOUT)
        server, _ = tcp_target.accept()
        got, times = bytearray(), []
        start = time.monotonic()
        client.sendall(data)
        client.shutdown(socket.SHUT_WR)
        receive_all(server, got, times)
        up = relay.up
        client.close()
        server.close()
    assert bytes(got) == data
    assert up.retransmitted > 0
    assert times[-1] - start >= profile.rto_s


def test_tcp_passes_end_of_stream_both_ways_and_refusals(tcp_target):
    with TcpRelay(Profile(delay=0.002), tcp_target.getsockname()) as relay:
        client = socket.create_connection(relay.address, timeout=TIMEOUT)
        server, _ = tcp_target.accept()
        server.settimeout(TIMEOUT)
        client.sendall(b"request")
        client.shutdown(socket.SHUT_WR)
        got = bytearray()
        while chunk := server.recv(100):
            got += chunk
        assert got == b"request"
        server.sendall(b"answer")
        server.close()
        got = bytearray()
        while chunk := client.recv(100):
            got += chunk
        assert got == b"answer"
        client.close()
        assert relay.wait_until(lambda up, down: relay.connections == 0, TIMEOUT)
    nobody = socket.socket()
    nobody.bind(("127.0.0.1", 0))                          # bound, never listening: refused
    with TcpRelay(Profile(), nobody.getsockname()) as relay:
        client = socket.create_connection(relay.address, timeout=TIMEOUT)
        try:
            assert client.recv(10) == b""
        except ConnectionResetError:
            pass
        assert relay.wait_until(lambda up, down: relay.connect_failed == 1, TIMEOUT)
        client.close()
    nobody.close()


# --- shutting down ----------------------------------------------------------------------

def test_close_is_prompt_and_leaves_no_threads(udp, tcp_target):
    before = set(threading.enumerate())
    target = udp()
    client = udp()
    slow = Profile(rate=1e5, delay=1.0)                    # much left in flight at close
    udp_relay = UdpRelay(slow, target.getsockname())
    tcp_relay = TcpRelay(slow, tcp_target.getsockname())
    for i in range(20):
        client.sendto(numbered(i, 1000), udp_relay.address)
    connection = socket.create_connection(tcp_relay.address, timeout=TIMEOUT)
    server, _ = tcp_target.accept()
    connection.sendall(bytes(100_000))
    assert udp_relay.wait_until(lambda up, down: up.datagrams_in == 20, TIMEOUT)
    assert tcp_relay.wait_until(lambda up, down: up.bytes_in > 0, TIMEOUT)
    assert len(set(threading.enumerate()) - before) == 3 + 1 + 4
    start = time.monotonic()
    udp_relay.close()
    tcp_relay.close()
    assert time.monotonic() - start < 1.0
    assert set(threading.enumerate()) == before
    udp_relay.close()                                      # idempotent
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as again:
        again.bind(udp_relay.address)                      # its socket is closed
    server.settimeout(TIMEOUT)
    try:                                                   # the far side sees the end
        assert server.recv(1 << 20) == b""
    except ConnectionResetError:
        pass
    connection.close()
    server.close()


# --- as a process of its own ------------------------------------------------------------

def test_the_command_line_relays_and_reports_its_counters(udp):
    target, sink = udp(sink=True)
    client = udp()
    port = target.getsockname()[1]
    process = subprocess.Popen(
        [sys.executable, "-m", "rosgate_emulator", "udp", "--preset", "wifi",
         "--loss", "0", "--target", f"127.0.0.1:{port}"],
        stdout=subprocess.PIPE, text=True)
    try:
        first = process.stdout.readline().split()
        assert first[0] == "udp" and first[2] == "->" and first[3] == f"127.0.0.1:{port}"
        host, _, listen = first[1].rpartition(":")
        client.sendto(b"through", (host, int(listen)))
        assert sink.wait_for(1)
        assert sink.data == [b"through"]
        process.send_signal(signal.SIGTERM)
        out, _ = process.communicate(timeout=TIMEOUT)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    counters = json.loads(out.strip().splitlines()[-1])
    assert counters["up"]["datagrams_delivered"] == 1
    assert process.returncode == 0


# --- real kernel links (root only) ------------------------------------------------------

netns = pytest.mark.skipif(NetnsPair.unavailable() is not None,
                           reason=f"NetnsPair: {NetnsPair.unavailable()}")


def namespaces() -> set[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return {line.split()[0] for line in out.splitlines() if line.strip()}


@netns
def test_netns_pair_echoes_udp_and_is_deleted_even_after_errors():
    with pytest.raises(RuntimeError, match="inside"):
        with NetnsPair() as pair:
            names = set(pair.namespaces.values())
            assert names <= namespaces()
            shown = pair.run("a", ["ip", "-4", "-o", "addr", "show", "dev", "va"],
                             capture_output=True, text=True, check=True).stdout
            assert pair.address("a") in shown
            server = pair.socket("b")
            client = pair.socket("a")
            try:
                server.bind((pair.address("b"), 0))
                server.settimeout(TIMEOUT)
                client.settimeout(TIMEOUT)
                echo = threading.Thread(target=lambda: server.sendto(*server.recvfrom(2000)))
                echo.start()
                client.sendto(b"ping across", server.getsockname())
                assert client.recvfrom(2000) == (b"ping across", server.getsockname())
                echo.join(TIMEOUT)
                with pytest.raises(OSError):           # the test process's own stack has no 10.99
                    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as outside:
                        outside.bind((pair.address("a"), 0))
            finally:
                server.close()
                client.close()
            raise RuntimeError("an error inside the with block")
    assert not names & namespaces()


@netns
def test_netns_tbf_caps_a_bulk_udp_send():
    rate, size, seconds = 8e6, 1400, 2.0
    wire = size + 28 + 14                              # tbf counts the Ethernet header too
    with NetnsPair(rate=rate) as pair:
        receiver = pair.socket("b")
        sender = pair.socket("a")
        try:
            receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BUFFER)
            receiver.bind((pair.address("b"), 0))
            sink = Sink(receiver)
            per_tick = 10
            interval = per_tick * wire * 8 / (2 * rate)   # offers twice the rate
            start = tick = time.monotonic()
            while time.monotonic() - start < seconds:
                for _ in range(per_tick):
                    try:        # a full tbf queue drops, or blocks us on our socket buffer
                        sender.sendto(bytes(size), receiver.getsockname())
                    except OSError:
                        pass
                tick += interval
                time.sleep(max(0.0, tick - time.monotonic()))     # pacing the sender
            while sink.wait_for(len(sink.items) + 1, timeout=0.3):
                pass                                   # until tbf's queue has drained
            sink.close()
        finally:
            receiver.close()
            sender.close()
    times = [t for t, _, _ in sink.items]              # stamped by the kernel on arrival
    assert times[-1] - times[0] > 0.75 * seconds
    measured = (len(times) - 1) * wire * 8 / (times[-1] - times[0])
    assert measured == pytest.approx(rate, rel=0.10)
