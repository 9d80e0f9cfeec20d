"""``rosgate top`` in a real pseudo-terminal (pexpect) against a running client/server pair of
``rosgate run`` processes: the rates it shows match what a probe publishes, a drop shows with
its reason within 2 s, a key sorts, q and Ctrl-C quit cleanly."""

from __future__ import annotations

import os
import re
import subprocess
import tempfile
import time
from pathlib import Path

import pexpect
import pytest
from conftest import ROSGATE, free_port
from test_status import Publisher

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b[()][A-Z0-9]|\r")


@pytest.fixture
def runtime_dir(monkeypatch):
    with tempfile.TemporaryDirectory(prefix="rg", dir="/tmp") as folder:
        monkeypatch.setenv("ROSGATE_RUNTIME_DIR", folder)
        yield Path(folder)


class Top:
    """``rosgate top`` in a pseudo-terminal; ``screen`` is all it drew, without escapes."""

    def __init__(self, *args: str):
        self.child = pexpect.spawn(ROSGATE, ["top", *args], env=dict(os.environ, TERM="xterm"),
                                   dimensions=(60, 220), encoding="utf-8", codec_errors="replace",
                                   timeout=10)
        self.screen = ""

    def read(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                self.screen += ANSI.sub("", self.child.read_nonblocking(1 << 16, 0.1))
            except pexpect.TIMEOUT:
                pass
            except pexpect.EOF:
                return

    def wait_for(self, pattern: str, timeout: float) -> re.Match[str] | None:
        start = len(self.screen)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.read(0.1)
            found = re.search(pattern, self.screen[start:])
            if found:
                return found
        return None

    def rows(self, name: str) -> list[list[str]]:
        """Every drawn row of the topic table for ``name``, as its cells."""
        out = []
        for line in self.screen.split("\n"):
            cells = [c.strip() for c in line.split("│")[1:-1]]
            if cells and cells[0] == name:
                out.append(cells)
        return out

    def quit_with(self, key: str) -> int:
        if key == "ctrl-c":
            self.child.sendintr()
        else:
            self.child.send(key)
        self.child.expect(pexpect.EOF, timeout=10)
        self.child.close()
        return self.child.exitstatus


def test_top_shows_rates_drops_and_quits(tmp_path, domain, ros_side, bridge, runtime_dir):
    port = free_port()
    dc, ds = domain(), domain()
    server = tmp_path / "server.yaml"
    server.write_text(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    client = tmp_path / "client.yaml"
    client.write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /flow, type: std_msgs/msg/String, direction: transmit, qos: 100}}
  - {{topic: /limited, type: std_msgs/msg/String, direction: transmit, max_rate: 5}}
""")
    bridge(server, ds)
    bridge(client, dc, ready="server 'base' up")  # connected: the topics have routes
    robot = ros_side(dc, "robot")
    probe = Publisher(robot, 200, "p" * 200)
    try:
        top = Top(str(client))  # by its file
        assert top.wait_for(r"/flow", 10), top.screen
        top.read(2.0)  # rates settle
        started, count = time.monotonic(), probe.count
        top.read(4.0)
        published = (probe.count - count) / (time.monotonic() - started)
        shown = [float(cells[4]) for cells in top.rows("/flow")[-3:]]
        assert all(abs(rate - published) <= 0.1 * published for rate in shown), (
            shown, published)
        flow = top.rows("/flow")[-1]
        assert flow[1:4] == ["topic", "out", "base"]
        assert flow[6].endswith("kB") and flow[-1] == "-"  # bytes out per second; no drops
        assert "peers: base up" in top.screen and "links" in top.screen

        limited = Publisher(robot, 50, "l", topic="/limited")
        try:
            t0 = time.monotonic()  # the first drop comes with the second message
            assert top.wait_for(r"rate_limit=\d+", 2.0), top.screen[-3000:]
            assert time.monotonic() - t0 <= 2.0
        finally:
            limited.close()
        assert top.rows("/limited")[-1][-1].startswith("rate_limit=")

        top.child.send("s")  # sort by out/s: the busiest first
        assert top.wait_for(r"OUT/S ▼", 3), top.screen[-3000:]
        assert top.quit_with("q") == 0
    finally:
        probe.close()

    by_name = Top("robot1")
    assert by_name.wait_for(r"rosgate robot1 \(client\)", 10), by_name.screen
    assert by_name.quit_with("ctrl-c") == 0


def test_top_without_a_bridge_says_so(runtime_dir):
    top = Top("nobody")
    top.child.expect(pexpect.EOF, timeout=30)
    top.child.close()
    assert top.child.exitstatus == 2
    assert "no bridge named 'nobody' is running" in top.child.before
    alone = Top()
    alone.child.expect(pexpect.EOF, timeout=30)
    assert "no rosgate bridge is running on this machine" in alone.child.before


def test_top_once_prints_one_frame(tmp_path, domain, bridge, runtime_dir):
    server = tmp_path / "server.yaml"
    server.write_text(f"bridge: {{name: base, role: server, server: 127.0.0.1:{free_port()}}}\n")
    bridge(server, domain())
    out = ANSI.sub("", pexpect.run(f"{ROSGATE} top base --once --interval 0.2",
                                   encoding="utf-8", codec_errors="replace", timeout=20,
                                   env=dict(os.environ, COLUMNS="160")))
    assert "q: quit" not in out
    assert "rosgate base (server)" in out and "topics and services" in out and "links" in out


def test_top_once_into_a_pipe_prints_every_row_whole(tmp_path, domain, bridge, runtime_dir):
    """Not a terminal (a pipe, a file, grep): plain text, no escapes, and a row as wide as it
    needs, where rich alone would cut it at 80 columns."""
    name = "/robot1/sensors/front_left_stereo_camera/image_rect_color/compressed_for_the_base"
    peer = tmp_path / "peer.yaml"
    peer.write_text(
        f"bridge: {{name: far, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, insecure: true}}\n"
        f"topics:\n  - {{topic: {name}, type: std_msgs/msg/String, direction: transmit, "
        f"port: {free_port()}}}\n")
    bridge(peer, domain())
    result = subprocess.run([ROSGATE, "top", "far", "--once", "--interval", "0.2"],
                            capture_output=True, text=True, timeout=30,
                            env={k: v for k, v in os.environ.items() if k != "COLUMNS"})
    assert result.returncode == 0, result.stderr
    assert "\x1b" not in result.stdout
    row = next(line for line in result.stdout.splitlines() if "/robot1/" in line)
    assert name in row and "topic" in row and len(row) > 100, result.stdout
