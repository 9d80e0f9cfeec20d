"""``rosgate router``, the zenoh plugin's command, as a real process: it routes (a zenoh client,
which opens only when a router answers, opens through it), it stops cleanly on SIGTERM, and it
is the plugin's: with the plugin blocked the verb is gone and the rest of ``rosgate`` works."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import zenoh
from rosgate_testing import free_port

ROSGATE = str(Path(sys.executable).with_name("rosgate"))


def client_through(endpoint: str) -> list[str]:
    """The routers a zenoh client in mode client finds at ``endpoint`` (it opens only with one)."""
    session = zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "client", "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}}})))
    try:
        return [str(z) for z in session.info.routers_zid()]
    finally:
        session.close()


def _untimed(line: str) -> str:
    """A log line without the time it starts with (ISO 8601, milliseconds, the zone's offset)."""
    stamp, rest = line.split(" ", 1)
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}[+-]\d{4}", stamp), line
    return rest


def test_router_routes_until_sigterm_and_says_where_it_listens():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen([ROSGATE, "router", "--listen", endpoint], stderr=subprocess.PIPE,
                              text=True)
    try:
        assert router.stderr is not None
        assert _untimed(router.stderr.readline()) == \
            f"[rosgate] INFO zenoh router running, listening on {endpoint}\n"
        assert len(client_through(endpoint)) == 1
    finally:
        router.send_signal(signal.SIGTERM)
        assert router.wait(10) == 0
    assert "".join(map(_untimed, router.stderr.readlines())) == (
        "[rosgate] WARNING the router runs without TLS: any zenoh session that reaches it may "
        "join (rosgate router --tls DIR, docs/fleets.md)\n[rosgate] INFO stopping\n")


def test_router_help_names_its_options():
    result = subprocess.run([ROSGATE, "router", "--help"], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0
    assert result.stdout.startswith("usage: rosgate router [-h] [--listen ENDPOINT] [--config "
                                    "FILE] [--tls DIR]\n")
    for option in ("[--robot NAME]", "[--base NAME]", "[--prefix PREFIX]"):
        assert option in result.stdout
    assert "(default tcp/0.0.0.0:7447" in result.stdout
    assert "tls/0.0.0.0:7447 with --tls" in " ".join(result.stdout.split())


def test_router_is_the_plugin_s_verb_gone_when_the_plugin_is_blocked(tmp_path):
    env = dict(os.environ, ROSGATE_DISABLE_PLUGINS="zenoh")
    gone = subprocess.run([ROSGATE, "router"], capture_output=True, text=True, timeout=60,
                          env=env)
    assert gone.returncode == 2
    assert "rosgate: error: argument COMMAND: invalid choice: 'router'" in gone.stderr
    key = tmp_path / "id.key"
    made = subprocess.run([ROSGATE, "keygen", "identity", "--out", str(key)],
                          capture_output=True, text=True, timeout=60, env=env)
    assert made.returncode == 0 and key.stat().st_size > 0, made.stderr
