"""Admission without a network: which connection gives its place up to a newer one, and the
recent clients a server keeps in its state folder across restarts."""

from __future__ import annotations

import json
import os
import stat

import pytest

from rosgate.admission import ConnectionLimits, Place, RecentHosts
from rosgate.drops import Drop


class Clock:
    def __init__(self, now: float = 1_000_000.0):
        self.now = now

    def __call__(self) -> float:
        return self.now


def take(limits: ConnectionLimits, host: str, evicted: list[str]) -> Place | Drop:
    return limits.take(host, lambda: evicted.append(host))


def test_a_stranger_takes_back_the_oldest_idle_stranger_place_and_no_recent_one():
    recent = RecentHosts(clock=Clock())
    recent.remember("10.0.0.1")
    limits = ConnectionLimits(8, 8, recent)  # 6 open to all, 2 kept for recent hosts
    evicted: list[str] = []
    robot = take(limits, "10.0.0.1", evicted)
    assert isinstance(robot, Place)
    strangers = [take(limits, f"10.0.1.{n}", evicted) for n in range(5)]
    assert all(isinstance(p, Place) for p in strangers) and limits.held == 6
    # the open places are held: the next stranger takes the oldest stranger's, not the robot's
    newcomer = take(limits, "10.0.2.1", evicted)
    assert isinstance(newcomer, Place)
    assert evicted == ["10.0.1.0"] and limits.held == 6
    # the evicted connection's own release changes nothing
    limits.give_back(strangers[0])  # type: ignore[arg-type]
    assert limits.held == 6


def test_idle_places_go_first_then_those_in_a_handshake_and_proven_ones_never():
    limits = ConnectionLimits(3, 3, RecentHosts(clock=Clock()))  # 2 open to all, 1 kept
    evicted: list[str] = []
    a, b = take(limits, "a", evicted), take(limits, "b", evicted)
    assert isinstance(a, Place) and isinstance(b, Place)
    a.heard()  # a has begun its handshake: b, idle, goes first though younger
    assert isinstance(take(limits, "c", evicted), Place)
    assert evicted == ["b"]
    limits2 = ConnectionLimits(2, 2, RecentHosts(clock=Clock()))  # 1 open to all
    p = take(limits2, "a", evicted)
    assert isinstance(p, Place)
    p.prove()
    assert take(limits2, "d", evicted) is Drop.TOO_MANY_CONNECTIONS
    assert evicted == ["b"]


def test_a_full_source_takes_nothing_back():
    limits = ConnectionLimits(4, 1, RecentHosts(clock=Clock()))
    evicted: list[str] = []
    assert isinstance(take(limits, "a", evicted), Place)
    assert take(limits, "a", evicted) is Drop.TOO_MANY_PER_SOURCE
    assert evicted == []


def test_recent_hosts_are_kept_across_a_restart_in_a_private_file(tmp_path):
    clock = Clock()
    path = tmp_path / "base.recent-hosts.json"
    first = RecentHosts(path, clock)
    first.remember("127.0.0.1")
    first.remember("10.0.0.7")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert set(json.loads(path.read_text())["hosts"]) == {"127.0.0.1", "10.0.0.7"}
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # nothing left aside
    clock.now += 3600
    again = RecentHosts(path, clock)  # the server restarted
    assert "127.0.0.1" in again and "10.0.0.7" in again and "10.0.0.8" not in again
    clock.now += RecentHosts.FOR
    assert "127.0.0.1" not in RecentHosts(path, clock)  # a day old: a stranger again


def test_the_kept_file_is_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(RecentHosts, "KEEP", 3)
    clock = Clock()
    path = tmp_path / "recent.json"
    hosts = RecentHosts(path, clock)
    for n in range(5):
        clock.now += 1
        hosts.remember(f"10.0.0.{n}")
    kept = json.loads(path.read_text())["hosts"]
    assert sorted(kept) == ["10.0.0.2", "10.0.0.3", "10.0.0.4"]


@pytest.mark.parametrize("content", [b"not json", b'{"hosts": 3}', b"[]", b"{" * 300_000,
                                     b'{"hosts": {"10.0.0.1": "soon"}}'])
def test_a_kept_file_that_cannot_be_read_is_said_and_started_afresh(tmp_path, caplog, content):
    path = tmp_path / "recent.json"
    path.write_bytes(content)
    hosts = RecentHosts(path, Clock())
    assert "10.0.0.1" not in hosts
    assert "cannot read the recent clients kept there" in caplog.text
    hosts.remember("10.0.0.2")  # and it is replaced by a good one
    assert "10.0.0.2" in RecentHosts(path, Clock())


def test_a_file_that_cannot_be_written_is_said_and_the_server_goes_on(tmp_path, caplog):
    folder = tmp_path / "gone"
    hosts = RecentHosts(folder / "recent.json", Clock())
    hosts.remember("10.0.0.1")
    assert "10.0.0.1" in hosts
    assert "cannot keep the recent clients there" in caplog.text
    assert not folder.exists() and os.listdir(tmp_path) == []
