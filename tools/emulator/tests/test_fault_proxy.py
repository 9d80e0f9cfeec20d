"""The fault proxy (rosgate_emulator.faults) on its own: what it forwards, drops and doubles, as
its counters say, datagram by datagram, on real sockets; the end-to-end tests
(tests/test_faults.py) put it between bridges."""

from __future__ import annotations

import socket
import threading
import time

from rosgate_emulator import UdpFaults, UdpRates

TIMEOUT = 10.0


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_until(condition, timeout: float = TIMEOUT) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_datagrams_cross_dropped_and_doubled_as_counted_and_answers_come_back():
    target = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target.bind(("127.0.0.1", 0))
    target.settimeout(0.2)
    port = free_udp_port()
    proxy = UdpFaults(port, target.getsockname()[1], UdpRates(drop=0.3, duplicate=0.2), seed=5)
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.settimeout(TIMEOUT)
    arrived: list[bytes] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            try:
                data, sender = target.recvfrom(65536)
            except TimeoutError:
                continue
            arrived.append(data)
            if data == b"echo":
                target.sendto(b"answer", sender)

    reader = threading.Thread(target=receive, daemon=True)
    reader.start()
    try:
        sent = [f"datagram {n}".encode() for n in range(200)]
        for data in sent:
            client.sendto(data, ("127.0.0.1", port))
        counts = proxy.counts
        assert wait_until(lambda: counts["in"] == 200)
        # the echo goes last, faults off: once its answer is back, everything before it is in
        proxy.rates = UdpRates()
        client.sendto(b"echo", ("127.0.0.1", port))
        assert client.recvfrom(65536)[0] == b"answer"
        assert arrived.pop() == b"echo"
        assert 30 < counts["dropped"] < 90 and 10 < counts["duplicated"] < 60
        assert len(arrived) == 200 - counts["dropped"] + counts["duplicated"]
        assert set(arrived) <= set(sent)  # each one whole, none made up
        assert len(set(arrived)) == 200 - counts["dropped"]
        order = [sent.index(data) for data in arrived]
        assert order == sorted(order)  # no reordering asked: none happened
    finally:
        done.set()
        reader.join(2)
        proxy.close()
        client.close()
        target.close()
