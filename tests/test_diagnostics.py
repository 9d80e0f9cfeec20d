"""/diagnostics (rosgate-diagnostics): the levels and values a running bridge publishes, and the
key that turns it off. A real client/server pair in this process, ROS sides in their own
domains."""

from __future__ import annotations

import logging
import threading

import pytest
from conftest import free_port, wait_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from test_status import Publisher, pair, runtime_dir  # noqa: F401 (a fixture)

from rosgate.config import loads
from rosgate.errors import ConfigError

OK, WARN, ERROR = (int.from_bytes(level, "big") for level in
                   (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR))


class DiagnosticsInbox:
    def __init__(self, side):
        self.arrays: list[DiagnosticArray] = []
        self.cond = threading.Condition()
        side.ros.subscribe(DiagnosticArray, "/diagnostics", 10, self._put, False)

    def _put(self, array) -> None:
        with self.cond:
            self.arrays.append(array)
            self.cond.notify_all()

    def wait_status(self, name: str, level: int, timeout: float = 10.0):
        """The first status named ``name`` at ``level`` to arrive from now on."""
        found = []

        def seen() -> bool:
            for array in self.arrays[start:]:
                for s in array.status:
                    if s.name == name and s.level == bytes([level]):
                        found.append(s)
                        return True
            return False
        with self.cond:
            start = len(self.arrays)
            assert self.cond.wait_for(seen, timeout), (
                f"no {name} at level {level}; last: "
                + repr([(s.name, s.level, s.message) for a in self.arrays[-1:] for s in a.status]))
        return found[0]


def test_diagnostics_say_ok_warn_and_error(engines, domain, ros_side):
    server, client, ds, dc = pair(engines, domain, free_port())
    robot = ros_side(dc, "robot")
    inbox = DiagnosticsInbox(robot)
    publisher = Publisher(robot, 50)
    try:
        assert wait_until(lambda: client.status()["peers"][0]["up"], 20)
        flowing = inbox.wait_status("rosgate: robot1: topic /flow (to base)", OK)
        values = {kv.key: kv.value for kv in flowing.values}
        assert flowing.hardware_id == "robot1" and flowing.message == "ok"
        assert values["direction"] == "transmit" and values["peer"] == "base"
        assert values["type"] == "std_msgs/msg/String"
        assert int(values["sent"]) > 0 and int(values["bytes_sent"]) >= 100 * int(values["sent"])
        stale = inbox.wait_status("rosgate: robot1: topic /quiet (from base)", WARN)
        assert stale.message.startswith("stale: no message for")
        assert {kv.key: kv.value for kv in stale.values}["received"] == "0"
        link = inbox.wait_status("rosgate: robot1: peer base", OK)
        assert link.message == "up"
        server.stop()  # the peer goes down
        down = inbox.wait_status("rosgate: robot1: peer base", ERROR, 20)
        assert down.message == "down"
        entry_down = inbox.wait_status("rosgate: robot1: topic /flow (to base)", ERROR)
        assert entry_down.message == "peer base is down"
        assert int({kv.key: kv.value for kv in entry_down.values}["sent"]) > 0
    finally:
        publisher.close()


def test_drops_since_the_last_status_warn(engines, domain, ros_side):
    """A topic limited to 5 Hz and published at 50 drops rate_limit: WARN, with the count."""
    port = free_port()
    ds, dc = domain(), domain()
    engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}", ds)
    engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /flow, type: std_msgs/msg/String, direction: transmit, max_rate: 5}}
""", dc)
    robot = ros_side(dc, "robot")
    inbox = DiagnosticsInbox(robot)
    publisher = Publisher(robot, 50)
    try:
        warned = inbox.wait_status("rosgate: robot1: topic /flow (to base)", WARN, 20)
    finally:
        publisher.close()
    assert warned.message.startswith("dropped rate_limit=")
    values = {kv.key: kv.value for kv in warned.values}
    assert int(values["drops.rate_limit"]) > 0


@pytest.mark.usefixtures("runtime_dir")
def test_diagnostics_can_be_turned_off(engines, domain, ros_side):
    port = free_port()
    ds = domain()
    server = engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, "
                     "diagnostics: false}", ds)
    assert [m.name for m in server.monitors] == []
    side = ros_side(ds, "base")
    assert wait_until(lambda: server.status()["uptime"] > 1.5, 5)
    names = [name for name, _ in side.ros.node.get_topic_names_and_types()]
    assert "/diagnostics" not in names


def test_diagnostics_key_is_checked():
    with pytest.raises(ConfigError, match="bridge.diagnostics.*expected true or false"):
        loads("bridge: {name: a, role: server, server: 127.0.0.1:1, insecure: true, "
              "diagnostics: maybe}")


def test_without_its_plugin_a_bridge_runs_and_says_so_once(monkeypatch, logs):
    monkeypatch.setenv("ROSGATE_DISABLE_PLUGINS", "diagnostics")
    from rosgate.engine import Engine

    engine = Engine(loads("bridge: {name: a, role: server, server: 127.0.0.1:1, insecure: true}",
                          file="b.yaml")).prepare()
    assert engine._monitor_classes == []
    said = logs.having("a: no diagnostics: ")
    assert len(said) == 1, logs.messages
    assert "plugin 'diagnostics' is blocked by ROSGATE_DISABLE_PLUGINS" in said[0]
    assert "pip install rosgate-diagnostics, or set bridge.diagnostics: false" in said[0]


def test_asked_for_without_its_plugin_is_named(monkeypatch):
    monkeypatch.setenv("ROSGATE_DISABLE_PLUGINS", "diagnostics")
    from rosgate.engine import Engine

    config = loads("bridge: {name: a, role: server, server: 127.0.0.1:1, insecure: true,\n"
                   "         diagnostics: true}", file="b.yaml")
    with pytest.raises(ConfigError) as caught:
        Engine(config).prepare()
    assert "b.yaml:2: bridge.diagnostics: unknown monitor 'diagnostics'" in str(caught.value)
    assert "fix: pip install rosgate-diagnostics, or remove diagnostics:" in str(caught.value)


def test_without_its_plugin_installed_a_bridge_runs_silently(logs):
    """On by default, not installed (the README's install line leaves it out): nothing to say
    at INFO or WARNING; -v (DEBUG) still tells."""
    from rosgate.engine import Engine
    from rosgate.plugins import Plugins

    plugins = Plugins.discover()
    plugins._waiting = [ep for ep in plugins._waiting if ep.name != "diagnostics"]
    logger = logging.getLogger("rosgate")
    logger.setLevel(logging.DEBUG)
    engine = Engine(loads("bridge: {name: a, role: server, server: 127.0.0.1:1, insecure: true}",
                          file="b.yaml"), plugins).prepare()
    assert engine._monitor_classes == []
    said = logs.having("a: no diagnostics: ")
    assert len(said) == 1, logs.messages
    assert [r.levelno for r in logs.records if "no diagnostics" in r.getMessage()] == \
        [logging.DEBUG]
