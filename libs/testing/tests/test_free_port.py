"""free_port: from the kernel, or in turn from a range of the test run's own."""

from __future__ import annotations

import socket

import pytest
from rosgate_testing import free_port


def bindable(port: int) -> bool:
    try:
        for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
            with socket.socket(socket.AF_INET, kind) as s:
                s.bind(("127.0.0.1", port))
    except OSError:
        return False
    return True


def test_without_a_range_the_kernel_picks_a_port_free_for_tcp_and_udp(monkeypatch):
    monkeypatch.delenv("ROSGATE_TEST_PORTS", raising=False)
    port = free_port()
    assert 1024 <= port <= 65535
    assert bindable(port)


def test_a_range_is_handed_out_in_turn_every_other_port_and_a_taken_one_is_skipped(monkeypatch):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        anchor = probe.getsockname()[1]
    first, last = anchor - anchor % 8, anchor - anchor % 8 + 7
    monkeypatch.setenv("ROSGATE_TEST_PORTS", f"{first}-{last}")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        try:
            taken.bind(("127.0.0.1", first + 2))
        except OSError:
            pass  # taken by someone else already: skipped all the same
        free = [p for p in range(first, last + 1, 2) if bindable(p)]
        ports = [free_port() for _ in free]
    assert first + 2 not in free
    assert sorted(ports) == free, "each free port of the range once before any again"
    assert not {p + 1 for p in ports} & set(ports), "the port after one handed out stays free"
    for port in ports:
        assert bindable(port)


def test_a_range_with_no_free_port_is_an_error_that_names_it(monkeypatch):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        monkeypatch.setenv("ROSGATE_TEST_PORTS", f"{port}-{port + 1}")
        with pytest.raises(RuntimeError, match=f"no free port in ROSGATE_TEST_PORTS={port}-"):
            free_port()
