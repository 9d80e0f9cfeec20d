"""Another local user who gets to a bridge's folders first: the status folder made before the
bridge starts, a status socket served in it, and what ``rosgate top`` then shows. Real
``rosgate run`` and ``rosgate top`` processes; the squatter is a process of another uid
(``nobody``) where the test runs as root.

Each docstring gives what the attack got on the code before the defence and asserts what it
gets now.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import AUTH, ROSGATE, free_port

from rosgate import runtime

NOBODY = 65534
as_root = pytest.mark.skipif(os.getuid() != 0, reason="making another uid's files needs root")

#: an entry as a squatter (or a client naming its entries) writes it: rich markup and terminal
#: escapes (a window title, clear screen, a bell) in its name and its peer
HOSTILE = "/x[bold red]FAKE[/bold red]\x1b]0;owned\x07\x1b[2J"


def fake_status() -> dict:
    entry = {"kind": "topic", "name": HOSTILE, "direction": "transmit",
             "peer": "[blink]p[/]\x1b[5m", "type": "std_msgs/msg/String", "transport": "udp",
             "port": None, "sent": 1, "bytes_sent": 10, "received": 0, "bytes_received": 0,
             "lost": 0, "drops": {"\x1b[31mred": 1}, "queue": 0, "stale": None, "silence": None,
             "latency": None, "refused": None}
    return {"version": 1, "bridge": "robot1", "role": "client", "time": 1.0, "uptime": 1.0,
            "entries": [entry, dict(entry, name="/refused", refused="no [i]way[/i]\x1b[8m")],
            "peers": [{"name": "base\x1b[1m", "up": True}],
            "links": [{"name": "udp[u]\x1b[4m", "up": True, "frames_out": 1, "bytes_out": 10,
                       "packets_out": 1, "frames_in": 0, "bytes_in": 0, "packets_in": 0,
                       "queue": 0, "bandwidth": None, "rtt": None}],
            "link_drops": {}}


#: the squatter: made a process of uid nobody once everything it needs is imported, it makes
#: the folder (0700, its own), binds robot1.sock in it and answers every request with its status
SQUATTER = textwrap.dedent("""
    import json, os, socket, sys
    folder, answer = sys.argv[1], json.dumps(json.loads(sys.argv[2])).encode() + b"\\n"
    os.setgroups([]); os.setgid(%(uid)d); os.setuid(%(uid)d)
    os.mkdir(folder, 0o700)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(os.path.join(folder, "robot1.sock"))
    os.chmod(os.path.join(folder, "robot1.sock"), 0o777)
    server.listen(8)
    print("ready", flush=True)
    while True:
        conn, _ = server.accept()
        with conn, conn.makefile("rb") as lines:
            while lines.readline():
                conn.sendall(answer)
""") % {"uid": NOBODY}


@pytest.fixture
def shared_tmp() -> Iterator[Path]:
    """A folder like /tmp: anyone may make files in it (sticky), so another uid can squat."""
    with tempfile.TemporaryDirectory(prefix="rg", dir="/tmp") as folder:
        os.chmod(folder, 0o1777)
        yield Path(folder)


@pytest.fixture
def squatter(shared_tmp) -> Iterator[Path]:
    """The status folder another user made, serving a fake robot1: its path."""
    folder = shared_tmp / "run"
    proc = subprocess.Popen([sys.executable, "-c", SQUATTER, str(folder),
                             json.dumps(fake_status())], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
        assert folder.stat().st_uid == NOBODY
        yield folder
    finally:
        proc.kill()
        proc.wait()


def top(folder: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, COLUMNS="400", **{runtime.RUNTIME_VARIABLE: str(folder)})
    return subprocess.run([ROSGATE, "top", *args], env=env, capture_output=True, text=True,
                           timeout=60)


@as_root
def test_top_refuses_a_socket_another_user_serves(squatter):
    """The attack: nobody makes the status folder and serves robot1.sock in it with fake
    entries; the operator runs ``rosgate top robot1 --once``.

    Before: top drew the squatter's entries (FAKE, styled as it asked, and its escapes sent
    to the terminal). Now it checks the folder's and the socket's owner, and the serving
    process's: it refuses, naming the folder, its owner and the fix, and shows nothing."""
    done = top(squatter, "robot1", "--once", "--interval", "0.1")
    assert done.returncode != 0, done.stdout
    assert f"belongs to uid {NOBODY}, not to you" in done.stderr, done.stderr
    assert str(squatter) in done.stderr and "fix: remove it" in done.stderr
    assert "FAKE" not in done.stdout and "\x1b" not in done.stdout + done.stderr


@as_root
def test_a_bridge_refuses_a_status_folder_another_user_made(squatter, tmp_path, domain):
    """The attack: nobody has made the status folder before the bridge starts.

    Before: the bridge ran on without a status socket (a warning), and ``rosgate top`` read
    the squatter's. Now ``rosgate run`` refuses to start: one message naming the folder, its
    owner and the fix, no traceback, exit code 2."""
    path = tmp_path / "b.yaml"
    path.write_text(AUTH.secure(f"""
bridge: {{name: robot1, role: server, server: 127.0.0.1:{free_port()}}}
"""))
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain()),
               **{runtime.RUNTIME_VARIABLE: str(squatter)})
    done = subprocess.run([ROSGATE, "run", str(path)], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2, done.stderr
    assert f"{squatter} is another user's (uid {NOBODY}), mode 700" in done.stderr, done.stderr
    assert f"point {runtime.RUNTIME_VARIABLE} at a folder of yours" in done.stderr
    assert "Traceback" not in done.stderr and "running as" not in done.stderr


def test_top_shows_markup_and_terminal_escapes_as_text(tmp_path, monkeypatch):
    """The attack: a status whose names carry rich markup and terminal escapes (a client
    names its entries; a refusal quotes them), read by ``rosgate top --once``.

    Before: the markup was applied (``FAKE`` drawn bold red, the brackets gone) and the
    escapes reached the terminal (a window title, a cleared screen). Now every word is
    shown as written: the markup in brackets, each control character as its escape."""
    folder = tmp_path / "run"
    monkeypatch.setenv(runtime.RUNTIME_VARIABLE, str(folder))
    server = runtime.StatusServer("robot1", fake_status)
    try:
        done = top(folder, "robot1", "--once", "--interval", "0.1")
    finally:
        server.close()
    assert done.returncode == 0, done.stderr
    assert "\x1b" not in done.stdout and "\x07" not in done.stdout
    for shown in ("/x[bold red]FAKE[/bold red]\\x1b]0;owned\\x07\\x1b[2J",
                  "[blink]p[/]\\x1b[5m", "refused: no [i]way[/i]\\x1b[8m", "base\\x1b[1m up",
                  "udp[u]\\x1b[4m", "\\x1b[31mred=1"):
        assert shown in done.stdout, (shown, done.stdout)


@as_root
def test_a_server_refuses_a_state_folder_another_user_made(squatter, tmp_path, domain):
    """The same squat on the folder where a server keeps its recent clients (whoever could
    write there could give their own addresses the places kept for robots): ``rosgate run``
    refuses to start, naming the folder and ``ROSGATE_STATE_DIR``."""
    path = tmp_path / "b.yaml"
    path.write_text(AUTH.secure(f"""
bridge: {{name: base, role: server, server: 127.0.0.1:{free_port()}}}
"""))
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain()),
               **{runtime.STATE_VARIABLE: str(squatter)})
    done = subprocess.run([ROSGATE, "run", str(path)], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2, done.stderr
    assert f"{squatter} is another user's (uid {NOBODY}), mode 700" in done.stderr, done.stderr
    assert f"point {runtime.STATE_VARIABLE} at a folder of yours" in done.stderr
    assert "Traceback" not in done.stderr and "running as" not in done.stderr
