"""``rosgate convert`` on the three real ros2_socket_bridge files (tests/data/legacy): the same
topics come out, ``rosgate check`` accepts both files, and a converted pair carries a topic."""

from __future__ import annotations

import importlib.util
import subprocess
from pathlib import Path

import pytest
import yaml
from conftest import ROSGATE, cross, free_port
from std_msgs.msg import String

LEGACY = Path(__file__).parent / "data" / "legacy"
FILES = sorted(p.name for p in LEGACY.glob("*.yaml"))


def convert(old: Path, folder: Path) -> tuple[Path, Path, str]:
    client, server = folder / "client.yaml", folder / "server.yaml"
    done = subprocess.run([ROSGATE, "convert", str(old), "-o", str(client), "--server-out",
                           str(server)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return client, server, done.stderr


def check(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                          timeout=60)


def old_topics(old: Path) -> list[tuple[str, str, int, str]]:
    params = next(iter(yaml.safe_load(old.read_text()).values()))["ros__parameters"]
    return [("/" + t.lstrip("/"), d, int(port), proto)
            for d in ("receive", "transmit")
            for t, port, proto in zip(params[f"{d}_topics"], params[f"{d}_ports"],
                                      params[f"{d}_protocols"], strict=True)]


def test_three_legacy_files_are_here():
    assert FILES == ["2_multibot_bringup.yaml", "bringup.yaml", "bringup_blu.yaml"]


@pytest.mark.parametrize("name", FILES)
def test_a_legacy_file_converts_to_files_check_accepts(name, tmp_path):
    old = LEGACY / name
    client, server, notes = convert(old, tmp_path)
    data = yaml.safe_load(client.read_text())
    transports = {"UDP": "udp", "TCP": "tcp", "BLUETOOTH": "bt"}
    got = [(t["topic"], t["direction"], t["port"], t["transport"]) for t in data["topics"]]
    assert got == [(n, d, p, transports[proto]) for n, d, p, proto in old_topics(old)]
    assert all(t["type"].count("/") == 2 for t in data["topics"])
    assert (tmp_path / "robot1.key").stat().st_mode & 0o777 == 0o600
    rules = yaml.safe_load(server.read_text())["clients"]["robot1"]["topics"]
    assert [(r["name"], r["direction"], r["ports"]) for r in rules] == [
        (n, d, [p]) for n, d, p, _ in old_topics(old)]
    assert f"{old}:" in notes and "pickle on the wire becomes cdr" in notes
    for path in (client, server):
        text = path.read_text()
        if "bt" in {t["transport"] for t in data["topics"]}:
            # this machine's Python has no AF_BLUETOOTH: the bt plugin's stand-in for a radio
            text += f"plugins: {{bt: {{emulate_dir: {tmp_path}}}}}\n"
        missing = {t["type"] for t in data["topics"]
                   if importlib.util.find_spec(t["type"].split("/")[0]) is None}
        if missing and path is client:
            # a message package not installed here (tf2_msgs): check names it, and the rest of
            # the file passes without those entries
            assert "tf2_msgs/msg/TFMessage: the package tf2_msgs is not installed" in notes
            path.write_text(text)
            assert "interface package 'tf2_msgs' is not installed" in check(path).stderr
            kept = yaml.safe_load(text)
            kept["topics"] = [t for t in kept["topics"] if t["type"] not in missing]
            text = yaml.safe_dump(kept, sort_keys=False)
        path.write_text(text)
        done = check(path)
        assert done.returncode == 0, done.stdout + done.stderr
        assert ": ok (" in done.stdout


def test_short_types_map_to_packages():
    from rosgate_convert.legacy import full_type

    assert full_type("String") == ("std_msgs/msg/String", None)
    assert full_type("PoseStamped") == ("geometry_msgs/msg/PoseStamped", None)
    assert full_type("Odometry") == ("nav_msgs/msg/Odometry", None)
    assert full_type("LaserScan") == ("sensor_msgs/msg/LaserScan", None)
    assert full_type("std_msgs/String") == ("std_msgs/msg/String", None)
    kind, why = full_type("NoSuchThing")
    assert kind == "unknown_msgs/msg/NoSuchThing" and "write its pkg/msg/Type" in why


def test_a_converted_pair_carries_a_topic(tmp_path, domain, ros_side, bridge):
    main, port = free_port(), free_port()
    old = tmp_path / "bringup.yaml"  # the real file, on ports free on this machine
    old.write_text((LEGACY / "bringup.yaml").read_text().replace("12000", str(main))
                   .replace("12001", str(port)))
    client, server, _ = convert(old, tmp_path)
    dc, ds = domain(), domain()
    bridge(server, ds)
    bridge(client, dc, ready="server 'server' up")
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    got = cross(base.publisher("/topic", String, 10), robot.listen("/topic", String, 10),
                lambda i: String(data="warmup" if i is None else f"converted-{i}"),
                lambda m: m.data == "warmup", 20, interval=0.01)
    assert [m.data for m in got] == [f"converted-{i}" for i in range(20)]


# -- hostile old files ---------------------------------------------------------------------------

def alias_bomb() -> str:
    """A kilobyte of nested aliases: nine lists of nine, nine deep, stand for 9**9 topics."""
    lines = ['a0: &a0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 9)]
    lines += ["client:", "  ros__parameters:", "    receive_topics: [*a8]",
              "    receive_msg_types: [String]"]
    return "\n".join(lines) + "\n"


def test_an_alias_bomb_is_refused_at_once_in_little_memory(tmp_path):
    """The attack: ``rosgate convert`` on a 1 kB old file of nested aliases.

    Before: it ran until killed (17 s and 1.6 GB to a MemoryError in the review; here killed
    at 10 s, at 290 MB and growing). Now the file is read within bounds (its aliases expanded
    to at most 100,000 values): refused with one message naming the file and the fix, within
    1 s and 100 MB (Python's allocations while converting, measured in this process)."""
    import time
    import tracemalloc

    from rosgate_convert.legacy import convert

    from rosgate import ConfigError

    text = alias_bomb()
    assert len(text) < 1024
    tracemalloc.start()
    started = time.monotonic()
    try:
        with pytest.raises(ConfigError, match="its aliases expand to more than 100000 values"):
            convert(text, "bomb.yaml")
        took = time.monotonic() - started
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert took < 1, f"{took:.1f} s"
    assert peak < 100 * 1024 * 1024, f"{peak // 1024 // 1024} MB"
    old = tmp_path / "bomb.yaml"
    old.write_text(text)
    done = subprocess.run([ROSGATE, "convert", str(old), "-o", str(tmp_path / "out.yaml")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    # the line of the list where the count passed the bound
    assert f"{old}:6: its aliases expand to more than 100000 values" in done.stderr, done.stderr
    assert "fix: write the lists out" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "out.yaml").exists()


def test_a_recursive_alias_is_refused():
    from rosgate_convert.legacy import read_yaml

    from rosgate import ConfigError

    with pytest.raises(ConfigError, match="refers to the list or mapping that contains it"):
        read_yaml("a: &a [1, *a]\n", "loop.yaml")


@pytest.mark.parametrize(("key", "value"), [("receive_topics", "/**"), ("receive_topics", "*"),
                                            ("transmit_topics", "robot?/cmd"),
                                            ("receive_msg_types", "*"),
                                            ("receive_msg_types", "geometry_msgs/msg/*")])
def test_a_pattern_in_an_old_file_is_refused(tmp_path, key, value):
    """The attack: an old file whose topic is ``/**`` (or a type ``*``).

    Before: it became a server rule allowing ``/**`` (port 22 with it), which ``rosgate
    check`` accepted. Now ``rosgate convert`` refuses it at its line, and writes nothing."""
    params = {"receive_topics": ["scan"], "receive_msg_types": ["LaserScan"],
              "receive_ports": [22], "receive_protocols": ["UDP"],
              "transmit_topics": ["cmd"], "transmit_msg_types": ["Twist"],
              "transmit_ports": [12002], "transmit_protocols": ["UDP"]}
    params[key] = [value]
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump({"client_node": {"ros__parameters": params}}))
    line = 1 + next(i for i, text in enumerate(old.read_text().splitlines())
                    if text.strip().startswith(f"{key}:"))
    done = subprocess.run([ROSGATE, "convert", str(old), "-o", str(tmp_path / "out.yaml")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert f"{old}:{line}: {key}[0]: {value!r} is a pattern, not a name" in done.stderr
    assert "fix: write each topic and type it carries by its name" in done.stderr
    assert not (tmp_path / "out.yaml").exists() and "clients:" not in done.stdout


@pytest.mark.parametrize(("rule", "warned"), [
    ("{name: /**, direction: both}", True),
    ("{name: '**', direction: transmit, types: ['**']}", True),
    ("{name: /**, direction: receive, types: ['*/*/*']}", True),
    ("{name: /**, direction: both, types: [geometry_msgs/msg/Twist]}", False),
    ("{name: /robot1/**, direction: both}", False),
])
def test_check_warns_on_a_rule_that_allows_everything(tmp_path, rule, warned):
    """The review's file: a server rule allowing ``/**`` with any type (what the old
    ``convert`` made of a ``/**`` topic), which ``rosgate check`` accepted without a word. Now
    check (and run) says it, at the rule's line; a rule bounded by name or type is quiet."""
    from conftest import AUTH

    path = tmp_path / "server.yaml"
    path.write_text(f"""bridge: {{name: base, role: server, server: 127.0.0.1:{free_port()},
         identity: {AUTH.identity("server")}}}
clients:
  robot1:
    key: {AUTH.public["robot1"]}
    topics:
      - {rule}
""")
    done = check(path)
    assert done.returncode == 0, done.stderr
    said = (f"{path}:7: clients.robot1.topics[0]: allows every name" in done.stderr
            and "robot1 may reach every topic of this server's ROS graph" in done.stderr)
    assert said == warned, done.stderr
