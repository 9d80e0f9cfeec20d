"""Only the fleet: zenoh's mutual TLS with certificates ``rosgate certs`` makes, and the access
control ``rosgate router --robot/--base`` enforces, against real ``rosgate router`` and
``rosgate run`` processes. Strangers cannot connect; a robot cannot send on another robot's
keys nor take what is addressed to another; nothing of theirs reaches ROS."""

from __future__ import annotations

import json
import subprocess
import time

import pytest
import zenoh
from conftest import ROSGATE, wait_until
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import String
from test_zenoh_fleet import Router

TIMEOUT = 20.0


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("certs")
    result = subprocess.run([ROSGATE, "certs", "--out", str(folder), "router", "robot1",
                             "robot2", "base"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    for name in ("ca", "router", "robot1", "robot2", "base"):
        assert (folder / f"{name}.pem").is_file()
        assert (folder / f"{name}.key").stat().st_mode & 0o077 == 0, "keys are the owner's"
    return folder


@pytest.fixture
def router(certs):
    r = Router("--tls", str(certs), "--robot", "robot1", "--robot", "robot2", "--base", "base",
               scheme="tls")
    yield r
    r.stop()


def session(router: Router, tls: dict | None) -> zenoh.Session:
    config = {"mode": "client", "connect": {"endpoints": [router.endpoint]},
              "scouting": {"multicast": {"enabled": False}}}
    if tls is not None:
        config["transport"] = {"link": {"tls": tls}}
    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


def as_bridge(certs, name: str) -> dict:
    return {"root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True,
            "connect_certificate": str(certs / f"{name}.pem"),
            "connect_private_key": str(certs / f"{name}.key"), "verify_name_on_connect": False}


@pytest.fixture
def robot1(tmp_path, certs, router, bridge, domain):
    d = domain()
    return bridge(robot1_file(tmp_path, certs, router), d), d


def robot1_file(tmp_path, certs, router: Router):
    """robot1's file: the zenoh plugin's default prefix, so its token is rosgate/robot1/@alive."""
    path = tmp_path / "robot1.yaml"
    path.write_text(f"""\
bridge: {{name: robot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}}}
plugins: {{zenoh: {{mode: client, connect: [{router.endpoint}], tls: {certs}}}}}
topics:
  - {{topic: /cmd, type: std_msgs/msg/String, direction: receive, framing: none,
      remote: fleet/robot1/cmd}}
  - {{topic: /odom, type: std_msgs/msg/String, direction: transmit, framing: none,
      remote: fleet/robot1/odom}}
""")
    return path


def test_a_session_without_a_certificate_cannot_connect(certs, router):
    with pytest.raises(zenoh.ZError):  # TLS, but no certificate of the fleet's CA
        session(router, {"root_ca_certificate": str(certs / "ca.pem")})
    with pytest.raises(zenoh.ZError):  # not even TLS
        session(router, None)
    base = session(router, as_bridge(certs, "base"))  # the control: a fleet certificate does
    base.close()


def test_a_robot_cannot_send_on_another_robots_keys_nor_take_them(certs, router, robot1,
                                                                   ros_side):
    _bridge, d = robot1
    side = ros_side(d, "robot1")
    inbox = side.listen("/cmd", String)
    odom = side.publisher("/odom", String)
    robot2 = session(router, as_bridge(certs, "robot2"))
    base = session(router, as_bridge(certs, "base"))
    stolen: list[bytes] = []
    robot2.declare_subscriber("fleet/robot1/**", zenoh.handlers.Callback(
        lambda s: stolen.append(s.payload.to_bytes()), indirect=False))
    seen: list[bytes] = []
    base.declare_subscriber("fleet/robot1/odom", zenoh.handlers.Callback(
        lambda s: seen.append(s.payload.to_bytes()), indirect=False))
    forged = robot2.declare_publisher("fleet/robot1/cmd")
    real = base.declare_publisher("fleet/robot1/cmd")
    deadline = time.monotonic() + TIMEOUT
    while not inbox.wait_count(1, 0.2):  # robot2 tries before and while the base succeeds
        assert time.monotonic() < deadline, "the base's command never reached robot1"
        forged.put(serialize_message(String(data="forged")))
        real.put(serialize_message(String(data="real")))
    for _ in range(20):
        forged.put(serialize_message(String(data="forged")))
    real.put(serialize_message(String(data="last")))
    assert inbox.wait_for(lambda items: items[-1].data == "last", TIMEOUT)
    assert {m.data for m in inbox.items} == {"real", "last"}, "0 forged messages reached ROS"

    deadline = time.monotonic() + TIMEOUT
    while not wait_until(lambda: bool(seen), 0.2):
        assert time.monotonic() < deadline, "robot1's odometry never reached the base"
        odom.publish(String(data="odom"))
    assert deserialize_message(seen[0], String).data == "odom"
    # robot2's session hands its own puts to its own subscriber (no router involved): those
    # alone, nothing addressed to robot1 (real, last) and nothing robot1 sent (odom)
    assert {deserialize_message(b, String).data for b in stolen} == {"forged"}
    for s in (robot2, base):
        s.close()


def test_with_default_prefixes_the_base_learns_a_robot_from_its_token(tmp_path, certs, router,
                                                                     bridge, domain):
    """The router's default --prefix (fleet) and the zenoh plugin's default prefix (rosgate)
    agree: robot1's token rosgate/robot1/@alive passes the access control, so the base knows
    robot1 before any data; a robot's session cannot hold another robot's token."""
    path = tmp_path / "base.yaml"
    path.write_text(f"""\
bridge: {{name: base, role: peer, defaults: {{transport: zenoh}}}}
plugins: {{zenoh: {{mode: client, connect: [{router.endpoint}], tls: {certs}}}}}
topics:
  - {{topic: '/{{robot}}/odom', type: std_msgs/msg/String, direction: receive,
     remote: 'fleet/{{robot}}/odom'}}
""")
    base = bridge(path, domain())
    robot2 = session(router, as_bridge(certs, "robot2"))
    try:  # robot2 claims robot1's token first, then its own, in order on one link
        _tokens = [robot2.liveliness().declare_token(f"{prefix}/{name}/@alive")
                   for name in ("robot1", "robot2") for prefix in ("rosgate", "fleet")]
        assert base.wait_log("fleet: robot robot2 joined (its liveliness token)", TIMEOUT), \
            base.log
        assert "robot robot1" not in base.log, "robot2 held robot1's token"
        bridge(robot1_file(tmp_path, certs, router), domain())  # no ROS publisher: no data
        assert base.wait_log("fleet: robot robot1 joined (its liveliness token)", TIMEOUT), \
            base.log
        assert "fleet: publishing" not in base.log, "robot1 was learned before any frame"
    finally:
        robot2.close()


BASE = """\
bridge: {name: base, role: peer, defaults: {transport: zenoh}%s}
plugins: {zenoh: {%s}}
topics:
  - {topic: '/{robot}/odom', type: std_msgs/msg/String, direction: receive,
     remote: 'fleet/{robot}/odom'}
"""
TLS_CA = "transport: {link: {tls: {root_ca_certificate: ca.pem%s}}}"
JUDGED = {  # zenoh's options -> the option refused, or None: every link authenticated
    "mode: client, connect: [tcp/127.0.0.1:7447]": "tls",
    "mode: client, connect: [tcp/127.0.0.1:7447], tls: certs": "connect",
    "mode: client, connect: [tls/127.0.0.1:7447], tls: certs": None,
    "mode: client, connect: [tls/127.0.0.1:7447, ws/127.0.0.1:7448], tls: certs": "connect",
    "mode: peer, connect: [tls/127.0.0.1:7447], tls: certs": "mode",
    "connect: [tls/127.0.0.1:7447], tls: certs": "mode",  # peer is the default
    "mode: router, listen: [tls/0.0.0.0:7447], tls: certs": None,
    "mode: peer, connect: [tls/127.0.0.1:7447], listen: [], tls: certs": None,
    "mode: peer, connect: [tls/127.0.0.1:7447], listen: [tls/0.0.0.0:0], tls: certs": None,
    "mode: peer, listen: {endpoints: {peer: [tcp/0.0.0.0:0]}}, tls: certs": "listen",
    "mode: client, connect: [tls/127.0.0.1:7447], tls: certs, "
    "scouting: {multicast: {enabled: true}}": "scouting",
    "mode: client, connect: [tls/127.0.0.1:7447], " + TLS_CA % ", enable_mtls: true": None,
    "mode: client, connect: [tls/127.0.0.1:7447], " + TLS_CA % "": "tls",  # no client certs
}


@pytest.mark.parametrize("zenoh_options", JUDGED)
def test_check_judges_every_link_of_the_session(zenoh_options):
    """A receiving entry without a keyed cipher is refused, at the zenoh option that leaves
    it open, unless mutual TLS guards every link the session has or can get; ``insecure:
    true`` (the file's one key) accepts it."""
    from rosgate.config import loads
    from rosgate.engine import Engine
    from rosgate.errors import ConfigError

    option = JUDGED[zenoh_options]
    text = BASE % ("", zenoh_options)
    if option is None:
        Engine(loads(text, file="base.yaml")).prepare()
        return
    with pytest.raises(ConfigError) as refused:
        Engine(loads(text, file="base.yaml")).prepare()
    e = refused.value
    assert (e.line, e.key) == (2, f"plugins.zenoh.{option}"), str(e)
    assert e.message.startswith("anyone who reaches this bridge can write to /{robot}/odom "
                                "(topics[0]): zenoh: "), e.message
    assert "bridge.insecure: true" in (e.fix or "")
    Engine(loads(BASE % (", insecure: true", zenoh_options), file="base.yaml")).prepare()
