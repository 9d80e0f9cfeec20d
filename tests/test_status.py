"""What a running bridge tells its operator: its status over the local socket and the summary
line (/diagnostics: test_diagnostics.py). A real client/server pair in this process, ROS sides
in their own domains."""

from __future__ import annotations

import logging
import os
import stat
import tempfile
import threading
import time
from pathlib import Path

import pytest
from conftest import free_port, wait_until
from rosgate_top.client import NoBridge, StatusClient, running
from std_msgs.msg import String

from rosgate import runtime
from rosgate.config import loads
from rosgate.errors import ConfigError


@pytest.fixture
def runtime_dir(monkeypatch):
    """A socket folder of the test's own (AF_UNIX paths must stay short)."""
    with tempfile.TemporaryDirectory(prefix="rg", dir="/tmp") as folder:
        path = Path(folder) / "run"
        monkeypatch.setenv(runtime.RUNTIME_VARIABLE, str(path))
        yield path


def pair(engines, domain, port: int, client_extra: str = "", server_extra: str = ""):
    ds, dc = domain(), domain()
    server = engines(f"""
bridge: {{name: base, role: server, server: 127.0.0.1:{port}{server_extra}}}
""", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, stale_after: 1{client_extra}}}
topics:
  - {{topic: /flow, type: std_msgs/msg/String, direction: transmit}}
  - {{topic: /quiet, type: std_msgs/msg/String, direction: receive}}
""", dc)
    return server, client, ds, dc


class Publisher:
    """Publishes ``topic`` at a steady rate in a thread of its own until stopped, from the
    moment the bridge's subscription is matched."""

    def __init__(self, side, rate: float, payload: str = "x" * 100, topic: str = "/flow"):
        self.pub = side.publisher(topic, String)
        assert wait_until(lambda: self.pub.get_subscription_count() > 0, 20), \
            f"no subscription to {topic}"
        self.rate, self.message = rate, String(data=payload)
        self.count = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        start = time.monotonic()
        while not self.stop.is_set():
            self.pub.publish(self.message)
            self.count += 1
            delay = start + self.count / self.rate - time.monotonic()
            if delay > 0:
                self.stop.wait(delay)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)


def entry(status, name):
    return next(e for e in status["entries"] if e["name"] == name)


def test_the_status_socket_tells_what_flows(engines, domain, ros_side, runtime_dir):
    server, client, ds, dc = pair(engines, domain, free_port())
    publisher = Publisher(ros_side(dc, "robot"), 100)
    listener = ros_side(ds, "base").listen("/flow", String)
    try:
        assert listener.wait_count(50, 20), "nothing crossed"
        folder = runtime_dir
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700
        sock = folder / "robot1.sock"
        assert stat.S_IMODE(sock.stat().st_mode) == 0o600
        assert sorted(running()) == ["base", "robot1"]
        with StatusClient("robot1") as ask:
            first = ask.status()
            time.sleep(1.0)  # a rate needs two statuses some time apart
            second = ask.status()
    finally:
        publisher.close()
    assert first["bridge"] == "robot1" and first["role"] == "client" and first["version"] == 1
    flow = entry(second, "/flow")
    assert (flow["kind"], flow["direction"], flow["peer"], flow["type"]) == (
        "topic", "transmit", "base", "std_msgs/msg/String")
    rate = (flow["sent"] - entry(first, "/flow")["sent"]) / (second["time"] - first["time"])
    assert 80 <= rate <= 120, rate
    assert flow["bytes_sent"] >= flow["sent"] * 100
    assert flow["stale"] is None and flow["refused"] is None
    quiet = entry(second, "/quiet")
    assert quiet["direction"] == "receive" and quiet["stale"] is True and quiet["received"] == 0
    assert second["peers"] == [{"name": "base", "up": True}]
    assert any(link["up"] and link["frames_out"] > 0 for link in second["links"])
    # the server sees the same topic, from robot1
    with StatusClient("base") as ask:
        seen = entry(ask.status(), "/flow")
    assert (seen["direction"], seen["peer"]) == ("receive", "robot1")
    assert seen["received"] >= 50


def test_no_bridge_is_a_clear_error(runtime_dir):
    with pytest.raises(NoBridge, match="no bridge named 'nobody' is running"):
        StatusClient("nobody")


def test_a_socket_left_by_a_dead_bridge_is_replaced_and_a_live_one_kept(runtime_dir):
    runtime_dir.mkdir(mode=0o700)
    (runtime_dir / "x.sock").touch()  # nobody answers there
    server = runtime.StatusServer("x", lambda: {"bridge": "x"})
    try:
        with StatusClient("x") as ask:
            assert ask.status() == {"bridge": "x"}
        with pytest.raises(OSError, match="another bridge named 'x'"):
            runtime.StatusServer("x", lambda: {})
    finally:
        server.close()
    assert not (runtime_dir / "x.sock").exists()


def test_a_socket_folder_others_may_enter_is_refused(runtime_dir):
    runtime_dir.mkdir(mode=0o755)
    os.chmod(runtime_dir, 0o755)
    with pytest.raises(runtime.NotPrivate, match="is open to others, mode 755"):
        runtime.StatusServer("x", lambda: {})


def test_metrics_without_its_plugin_is_named(monkeypatch):
    monkeypatch.setenv("ROSGATE_DISABLE_PLUGINS", "metrics")
    from rosgate.engine import Engine

    config = loads("bridge: {name: a, role: server, server: 127.0.0.1:1, insecure: true,\n"
                   "         metrics: 127.0.0.1:9108}", file="b.yaml")
    with pytest.raises(ConfigError) as caught:
        Engine(config).prepare()
    assert "b.yaml:2: bridge.metrics" in str(caught.value)
    assert "pip install rosgate-metrics-prometheus" in str(caught.value)


def test_the_summary_line_says_totals_and_what_is_wrong(engines, domain, ros_side, logs,
                                                        monkeypatch):
    from rosgate import engine as engine_module

    monkeypatch.setattr(engine_module, "STATS_EVERY", 2.0)
    port = free_port()
    ds, dc = domain(), domain()
    engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}", ds)
    engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, stale_after: 1}}
topics:
  - {{topic: /flow, type: std_msgs/msg/String, direction: transmit, max_rate: 5}}
  - {{topic: /quiet, type: std_msgs/msg/String, direction: receive}}
""", dc)
    publisher = Publisher(ros_side(dc, "robot"), 50)
    try:
        assert logs.wait("robot1: last ", 2, 20), logs.messages
    finally:
        publisher.close()
    line = logs.having("robot1: last ")[1]
    assert ": 2 topic(s), 0 service(s), sent " in line
    assert "drops rate_limit=" in line and "stale /quiet" in line
    assert logging.getLogger("rosgate").level == logging.INFO


def test_the_summary_line_counts_what_happened_since_the_last_one():
    from rosgate.status import IDLE, summary

    def row(name, direction="transmit", **counters):
        return {**IDLE, "kind": "topic", "name": name, "direction": direction, "peer": "base",
                **counters}

    before = {"bridge": "r", "time": 10.0, "uptime": 10.0, "peers": [], "entries": [
        row("/a", sent=5, bytes_sent=500, drops={"rate_limit": 2}),
        row("/q", "receive", received=1, bytes_received=100)]}
    now = {"bridge": "r", "time": 70.0, "uptime": 70.0,
           "peers": [{"name": "base", "up": False}, {"name": "b2", "up": None}], "entries": [
               row("/a", sent=15, bytes_sent=1500, drops={"rate_limit": 5, "queue_full": 1}),
               row("/q", "receive", received=4, bytes_received=400, stale=True),
               row("/s", kind="service", received=2, bytes_received=250),
               row("/no", refused="policy")]}
    assert summary(now, before) == (
        "r: last 60 s: 2 topic(s), 1 service(s), sent 10, received 5 (1.6 kB); "
        "drops queue_full=1, rate_limit=3; stale /q; down base; refused /no")
    # the first line counts from the start
    assert summary(before, None) == "r: last 10 s: 2 topic(s), 0 service(s), sent 5, " \
        "received 1 (600 B); drops rate_limit=2"


def test_counters_and_the_summary_line_go_on_across_a_new_policy(engines, domain, ros_side,
                                                                  logs):
    """A new policy (SIGHUP) that refuses a client's topic and another that allows it again
    tear its routes down and build them anew: the counters of a route that comes back go on
    from where they were, on both sides, and the summary line never says a negative count."""
    from dataclasses import replace

    from rosgate.config.clients import Rule
    from rosgate.status import summary

    server, client, ds, dc = pair(engines, domain, free_port())
    publisher = Publisher(ros_side(dc, "robot"), 100)
    listener = ros_side(ds, "base").listen("/flow", String)
    try:
        assert listener.wait_count(50, 20), "nothing crossed"
        before = {"base": server.status(), "robot1": client.status()}
        policy = server.config.clients["robot1"]  # /flow refused a while, then allowed again
        server.role.reload({"robot1": replace(policy, topics=(Rule("/quiet", "both"),))})
        assert logs.wait("client 'robot1': the new policy changed its entries", 1, 10)
        assert logs.wait("robot1: the server refused topics[0] (/flow)", 1, 10)
        server.role.reload({"robot1": policy})
        assert logs.wait("client 'robot1': the new policy changed its entries", 2, 10)
        count = len(listener.items)
        assert listener.wait_count(count + 50, 20), "nothing crossed after the new policy"
        # a message may reach the listener before its sender's thread has counted it sent
        wait_until(lambda: entry(client.status(), "/flow")["sent"]
                   >= entry(before["robot1"], "/flow")["sent"] + 50, 5)
        after = {"base": server.status(), "robot1": client.status()}
    finally:
        publisher.close()
    for side, key in (("base", "received"), ("robot1", "sent")):
        then, now = entry(before[side], "/flow")[key], entry(after[side], "/flow")[key]
        assert now >= then + 50, (side, then, now)
        line = summary(after[side], before[side])
        assert "-" not in line.split(": last ")[1].split(";")[0], line
