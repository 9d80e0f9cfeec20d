"""The fleet benchmark's TLS path, small: ``bench/fleet.py`` with 3 robots through a real
``rosgate router --tls DIR --base ... --robot ...`` (mutual TLS and access control) into a real
``rosgate run`` base with fleet entries; the simulated robots (``bench/fleet_robots.py``) are
zenoh TLS sessions, each presenting its own certificate from ``rosgate certs``; the counter
(``bench/fleet_counter.py``) compares every message the base publishes with what the robots
sent, field by field. So the code that makes the benchmark's TLS row cannot rot unseen. Beside
it, what that row relies on from the router's access control, at the zenoh level, and how
``rosgate check`` reads zenoh's own TLS options."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import zenoh
from conftest import ROSGATE, wait_until
from test_zenoh_fleet import Router
from test_zenoh_tls import TIMEOUT, as_bridge, session

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import fleet

ROBOTS = 3
SECONDS = 2.0


def test_every_message_of_a_small_tls_fleet_arrives_unchanged(tmp_path, domain):
    result = fleet.fleet(ROBOTS, SECONDS, tmp_path, True, domain=domain(), warm_up=1.0)
    assert result.tls
    robots = [f"robot{n:02d}" for n in range(ROBOTS)]
    for name in ("ca", "router", fleet.BASE, *robots):  # made by rosgate certs
        assert (tmp_path / "certs" / f"{name}.pem").is_file()
    assert "listening on tls/127.0.0.1:" in (tmp_path / "router.log").read_text()
    assert f"tls: {tmp_path / 'certs'}" in (tmp_path / "base.yaml").read_text()
    base = (tmp_path / "base.log").read_text()
    for robot in robots:  # each robot's token passed the router's access control
        assert f"fleet: robot {robot} joined (its liveliness token)" in base
    assert result.topics_published == ROBOTS * len(fleet.TOPICS)
    sent = round(SECONDS * 10) * ROBOTS  # 10 Hz, every robot, every topic
    assert result.sent == dict.fromkeys(fleet.TOPICS, sent)
    assert result.delivered == result.sent, "every message of the measured phase arrived"
    assert result.changed == 0, "each equal, field by field, to what its robot sent"
    assert result.problems == []
    assert result.met


def test_check_counts_zenohs_own_tls_options_as_tls(tmp_path):
    """A file may give zenoh's ``transport.link.tls`` itself instead of ``tls: DIR``: a
    cipherless fleet entry is then accepted as on a TLS bus, and refused without it (at the
    plugin's tls option)."""
    tls = ("transport: {link: {tls: {root_ca_certificate: certs/ca.pem, enable_mtls: true, "
           "connect_certificate: certs/base.pem, connect_private_key: certs/base.key}}}")
    text = ("bridge: {{name: base, role: peer, defaults: {{transport: zenoh}}}}\n"
            "plugins: {{zenoh: {{mode: client, connect: [tls/127.0.0.1:7447]{extra}}}}}\n"
            "topics:\n  - {{topic: '/{{robot}}/odom', type: std_msgs/msg/String, "
            "direction: receive, remote: 'fleet/{{robot}}/odom'}}\n")
    path = tmp_path / "base.yaml"
    results = {}
    for name, extra in (("zenoh's own", ", " + tls), ("none", "")):
        path.write_text(text.format(extra=extra))
        results[name] = subprocess.run([ROSGATE, "check", str(path)], capture_output=True,
                                       text=True, timeout=60)
    assert results["zenoh's own"].returncode == 0, results["zenoh's own"].stderr
    assert results["none"].returncode == 2
    refused = results["none"].stderr
    assert "plugins.zenoh.tls" in refused and "(topics[0])" in refused, refused


def test_through_the_access_control_a_robot_reaches_a_fleet_subscription(tmp_path):
    """What a base's fleet entry needs from ``rosgate router --tls --robot --base``: a robot's
    declared publisher puts on its own key into the base's ``fleet/*/odom`` (a key expression no
    robot owns, which the robot must still learn of, or its publisher sends nothing); its token
    under the router's prefix and under the plugin's default prefix reach the base, one it
    declares for another robot does not; and another robot hears none of it."""
    certs = fleet.certificates(tmp_path, ["robot1", "robot2"])
    router = Router("--tls", str(certs), "--robot", "robot1", "--robot", "robot2", "--base",
                    fleet.BASE, scheme="tls")
    sessions = []
    try:
        base, robot1, robot2 = (session(router, as_bridge(certs, name))
                                for name in (fleet.BASE, "robot1", "robot2"))
        sessions += [base, robot1, robot2]
        got: dict[str, list[str]] = {"base": [], "tokens": [], "robot2": []}

        def into(name: str):
            return zenoh.handlers.Callback(
                lambda s: got[name].append(f"{s.key_expr} {s.payload.to_bytes().decode()}"),
                indirect=False)

        base.declare_subscriber("fleet/*/odom", into("base"))
        for alive in ("fleet/*/@alive", "rosgate/*/@alive"):  # history: tokens declared before
            base.liveliness().declare_subscriber(alive, into("tokens"), history=True)  # it too
        robot2.declare_subscriber("fleet/robot1/**", into("robot2"))
        odom = robot1.declare_publisher("fleet/robot1/odom")
        _tokens = [robot1.liveliness().declare_token(key)  # robot2's first: refused
                   for key in ("rosgate/robot2/@alive", "fleet/robot2/@alive",
                               "rosgate/robot1/@alive", "fleet/robot1/@alive")]
        n = 0
        while not wait_until(lambda: bool(got["base"]), 0.2):
            assert n < 100, "robot1's publisher never reached the base's fleet subscription"
            n += 1
            odom.put(f"odom {n}")
        odom.put("last")
        assert wait_until(lambda: got["base"][-1] == "fleet/robot1/odom last", TIMEOUT)
        assert got["base"][-2:] == [f"fleet/robot1/odom odom {n}", "fleet/robot1/odom last"]
        assert wait_until(lambda: len({t.split()[0] for t in got["tokens"]}) >= 2, TIMEOUT)
        assert {t.split()[0] for t in got["tokens"]} == {"fleet/robot1/@alive",
                                                         "rosgate/robot1/@alive"}
        assert got["robot2"] == []
    finally:
        for s in sessions:
            s.close()
        router.stop()
