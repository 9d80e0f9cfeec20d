"""bringup.yaml with bus entries (zenoh): what a peer file on a bus may leave out, the keys it
gets, and one located error per mistake, through the resolver (which knows which transport is a
bus) exactly as ``rosgate check`` and ``rosgate run`` see them."""

from __future__ import annotations

import types

import pytest
from test_cli import rosgate, user_error

from rosgate import builtin
from rosgate.bus import BusRole, BusTransport
from rosgate.config import loads
from rosgate.engine import Engine
from rosgate.errors import ConfigError
from rosgate.plugins import Plugins

ZENOH = "plugins:\n  zenoh: {mode: client, connect: [tls/127.0.0.1:7447], tls: certs}\n"


def plan(text: str):
    return Engine(loads(text, file="bringup.yaml")).prepare().plan


def error(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        plan(text)
    return info.value


def test_a_peer_file_on_a_bus_needs_no_peer_listen_or_port():
    p = plan("bridge: {name: robot-1, role: peer, defaults: {transport: zenoh}}\n" + ZENOH + """\
topics:
  - {topic: /scan, type: sensor_msgs/msg/LaserScan, direction: transmit, qos: sensor_data}
  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: receive, remote: fleet/robot-1/cmd}
  - {topic: /camera/image, type: sensor_msgs/msg/Image, direction: transmit, framing: none,
     priority: background}
  - {topic: '/{robot}/odom', type: nav_msgs/msg/Odometry, direction: receive,
     remote: 'fleet/{robot}/odom', priority: 2}
services:
  - {service: /reset, type: std_srvs/srv/Trigger, direction: receive}
  - {service: '/{robot}/reset', type: std_srvs/srv/Trigger, direction: transmit,
     remote: 'fleet/{robot}/reset'}
""")
    assert [(t.key, t.delivery.priority, t.delivery.reliable) for t in p.topics] == [
        ("rosgate/robot-1/scan", 5, False),  # <prefix>/<bridge name>/<topic>
        ("fleet/robot-1/cmd", 5, True),      # remote: a key, as written
        ("camera/image", 7, True),           # framing none: the ROS name, as ros2dds keys it
        ("fleet/{robot}/odom", 2, True)]     # a template
    assert [s.key for s in p.services] == ["rosgate/robot-1/reset", "fleet/{robot}/reset"]


def test_priority_and_latest_only_reach_point_to_point_entries():
    """priority: was a bus-only key (zenoh's priorities); since real links it orders what waits
    in a link's scheduler, with the same names. latest_only defaults to the QoS: best effort
    replaces an unsent message, reliable queues it."""
    p = plan(PEER + """\
topics:
  - {topic: /a, type: std_msgs/msg/String, direction: transmit, port: 9, priority: 3}
  - {topic: /b, type: std_msgs/msg/String, direction: transmit, port: 9, qos: sensor_data}
  - {topic: /c, type: std_msgs/msg/String, direction: transmit, port: 9, qos: sensor_data,
     latest_only: false, priority: interactive_high}
  - {topic: /d, type: std_msgs/msg/String, direction: transmit, port: 9, latest_only: true,
     transport: tcp}
""")
    assert [(t.delivery.priority, t.delivery.latest_only) for t in p.topics] == [
        (3, False), (5, True), (2, False), (5, True)]


def test_prefix_and_namespace_options_make_the_default_keys():
    p = plan("bridge: {name: r1, role: peer, defaults: {transport: zenoh}}\n"
             "plugins: {zenoh: {prefix: fleet/a, namespace: /bot1}}\n"
             "topics:\n  - {topic: /x, type: std_msgs/msg/String, direction: transmit}\n"
             "  - {topic: /y, type: std_msgs/msg/String, direction: transmit, framing: none}\n")
    assert [t.key for t in p.topics] == ["fleet/a/r1/x", "bot1/y"]


def test_check_prints_each_entry_s_key(tmp_path):
    path = tmp_path / "robot.yaml"
    path.write_text("bridge: {name: r1, role: peer}\n" + ZENOH + "topics:\n"
                    "  - {topic: /x, type: std_msgs/msg/String, direction: transmit, "
                    "transport: zenoh}\n")
    result = rosgate("check", str(path))
    assert result.returncode == 0, result.stderr
    assert "/x -> rosgate/r1/x  [std_msgs/msg/String] zenoh cdr none" in result.stdout


PEER = "bridge: {name: r1, role: peer, peer: 127.0.0.1}\n" + ZENOH
BUS_PEER = "bridge: {name: r1, role: peer}\n" + ZENOH
TOPIC = "topics:\n  - {topic: /x, type: std_msgs/msg/String, direction: transmit, "
SERVICE = "services:\n  - {service: /s, type: std_srvs/srv/Trigger, direction: receive, "

ERRORS = {
    # what point-to-point entries of a peer need (moved here from config: only the resolver
    # knows whether a transport is a bus)
    "peer_without_peer": (
        BUS_PEER + TOPIC + "port: 9}\n", 1, "bridge.peer", "missing required key 'peer'"),
    "peer_topic_without_port": (
        PEER + TOPIC + "transport: udp}\n", 5, "topics[0].port",
        "peer role: each topic needs its own port"),
    "peer_service_without_port": (
        PEER + SERVICE + "transport: tcp}\n", 5, "services[0].port",
        "peer role: each service needs its own port"),
    # what a bus entry does not take
    "port_on_zenoh": (
        BUS_PEER + TOPIC + "transport: zenoh, port: 9}\n", 5, "topics[0].port",
        "port: does not apply to a zenoh topic"),
    "port_on_zenoh_service": (
        BUS_PEER + SERVICE + "transport: zenoh, port: 9}\n", 5, "services[0].port",
        "port: does not apply to a zenoh service"),
    "zenoh_in_client": (
        "bridge: {name: r1, role: client, server: 127.0.0.1:9}\n" + ZENOH + TOPIC
        + "transport: zenoh}\n", 5, "topics[0].transport",
        "zenoh is a bus: its topics belong in a file of role peer"),
    "serial_datagram_on_zenoh": (
        BUS_PEER + SERVICE + "transport: zenoh, framing: serial_datagram, codec: msgpack}\n",
        5, "services[0].transport", "framing serial_datagram needs a stream transport"),
    # what only a bus takes
    "placeholder_on_udp": (
        PEER + "topics:\n  - {topic: '/{robot}/x', remote: 'f/{robot}/x', port: 9, "
        "type: std_msgs/msg/String, direction: receive}\n", 5, "topics[0].topic",
        "placeholders such as {robot} need a bus transport"),
    "key_on_udp": (
        PEER + TOPIC + "port: 9, remote: fleet/robot-1/x}\n", 5, "topics[0].remote",
        "'fleet/robot-1/x' is not a valid ROS name"),
    # what a point-to-point link takes and a bus does not (README, "Real links")
    "recovery_on_zenoh": (
        BUS_PEER + TOPIC + "transport: zenoh, recovery: fec}\n", 5, "topics[0].recovery",
        "recovery: fec is for datagram links (udp): zenoh is a bus"),
    "recovery_on_tcp": (
        PEER + TOPIC + "transport: tcp, port: 9, recovery: retransmit}\n", 5,
        "topics[0].recovery", "tcp is a stream, which delivers whole and in order"),
    "latest_only_on_zenoh": (
        BUS_PEER + TOPIC + "transport: zenoh, latest_only: true}\n", 5, "topics[0].latest_only",
        "zenoh is a bus, which drops best-effort samples itself"),
    "budget_for_zenoh": (
        "bridge: {name: r1, role: peer, links: {zenoh: {bandwidth: 1mbit}}}\n" + ZENOH + TOPIC
        + "transport: zenoh}\n", 1, "bridge.links.zenoh", "zenoh is a bus"),
    "budget_for_an_unknown_transport": (
        "bridge: {name: r1, role: peer, peer: 127.0.0.1, links: {udpp: {bandwidth: 1mbit}}}\n"
        + TOPIC + "port: 9}\n", 1, "bridge.links.udpp", "udpp"),
    # placeholders (config)
    "unknown_placeholder": (
        BUS_PEER + "topics:\n  - {topic: '/{robt}/x', remote: 'f/{robt}/x', transport: zenoh, "
        "type: std_msgs/msg/String, direction: receive}\n", 5, "topics[0].topic",
        "unknown placeholder {robt}"),
    "placeholder_in_a_part": (
        BUS_PEER + "topics:\n  - {topic: '/r_{robot}/x', remote: 'f/{robot}/x', "
        "transport: zenoh, type: std_msgs/msg/String, direction: receive}\n", 5,
        "topics[0].topic", "not a valid ROS name"),
    "placeholder_without_remote": (
        BUS_PEER + "topics:\n  - {topic: '/{robot}/x', transport: zenoh, "
        "type: std_msgs/msg/String, direction: receive}\n", 5, "topics[0].topic",
        "needs remote: with the same placeholders"),
    "placeholder_missing_in_remote": (
        BUS_PEER + "topics:\n  - {topic: '/{robot}/x', remote: fleet/x, transport: zenoh, "
        "type: std_msgs/msg/String, direction: receive}\n", 5, "topics[0].remote",
        "must hold the same placeholders"),
    "placeholder_only_in_remote": (
        BUS_PEER + "topics:\n  - {topic: /x, remote: 'fleet/{robot}/x', transport: zenoh, "
        "type: std_msgs/msg/String, direction: receive}\n", 5, "topics[0].remote",
        "must hold the same placeholders"),
    "fleet_service_served_here": (
        BUS_PEER + "services:\n  - {service: '/{robot}/s', remote: 'f/{robot}/s', "
        "transport: zenoh, type: std_srvs/srv/Trigger, direction: receive}\n", 5,
        "services[0].direction", "a fleet service (with {robot}) is called here"),
    "priority_name": (
        BUS_PEER + TOPIC + "transport: zenoh, priority: urgent}\n", 5, "topics[0].priority",
        "expected a priority, 1 (real_time) to 7 (background)"),
    # the plugin's options, at the option's line: those it declares checked by rosgate, inside
    # zenoh's sections by zenoh, in its words
    "zenoh_unknown_option": (
        "bridge: {name: r1, role: peer}\nplugins:\n  zenoh:\n    mdoe: client\n" + TOPIC
        + "transport: zenoh}\n", 4, "plugins.zenoh.mdoe",
        "unknown key 'mdoe' (did you mean 'mode'?)"),
    "zenoh_bad_mode": (
        "bridge: {name: r1, role: peer}\nplugins:\n  zenoh:\n    mode: robot\n" + TOPIC
        + "transport: zenoh}\n", 4, "plugins.zenoh.mode",
        "'robot' is not one of peer, client, router"),
    "zenoh_unknown_nested_option": (
        "bridge: {name: r1, role: peer}\nplugins:\n  zenoh:\n    transport:\n      link:\n"
        "        tx: {leese: 1}\n" + TOPIC + "transport: zenoh}\n", 6,
        "plugins.zenoh.transport.link.tx.leese",
        "unknown zenoh option 'leese' under transport.link.tx"),
    "zenoh_nested_bad_value": (
        "bridge: {name: r1, role: peer}\nplugins:\n  zenoh:\n    scouting:\n      multicast:\n"
        "        enabled: 'no'\n" + TOPIC + "transport: zenoh}\n", 6,
        "plugins.zenoh.scouting.multicast.enabled", "expected a boolean"),
    "zenoh_bad_prefix": (
        "bridge: {name: r1, role: peer}\nplugins:\n  zenoh: {prefix: /fleet}\n" + TOPIC
        + "transport: zenoh}\n", 3, "plugins.zenoh.prefix", "no leading or trailing '/'"),
}


@pytest.mark.parametrize("text, line, key, message", ERRORS.values(), ids=ERRORS.keys())
def test_error(text, line, key, message):
    e = error(text)
    assert (e.file, e.line, e.key) == ("bringup.yaml", line, key), str(e)
    assert message in e.message, str(e)
    assert e.fix


def test_a_wrong_zenoh_option_is_one_clear_message_from_the_cli(tmp_path):
    path = tmp_path / "robot.yaml"
    path.write_text("bridge: {name: r1, role: peer}\nplugins:\n  zenoh: {mode: robot}\n" + TOPIC
                    + "transport: zenoh}\n")
    text = user_error(rosgate("check", str(path)))
    assert f"{path}:3: plugins.zenoh.mode: 'robot' is not one of peer, client, router" in text


def test_run_without_the_router_a_client_needs_is_one_clear_message(tmp_path):
    from rosgate_testing import free_port

    path = tmp_path / "robot.yaml"
    path.write_text("bridge: {name: r1, role: peer}\nplugins:\n  zenoh: {mode: client, connect: "
                    f"[tcp/127.0.0.1:{free_port()}]}}\n" + TOPIC + "transport: zenoh}\n")
    text = user_error(rosgate("run", str(path)))
    assert f"{path}:5: topics[0].transport: zenoh: cannot open a session: Unable to connect" \
        in text
    assert "mode: peer opens without one" in text


def test_router_takes_zenoh_s_own_config_file_and_refuses_a_bad_endpoint(tmp_path):
    import json
    import signal
    import subprocess

    import zenoh
    from conftest import ROSGATE
    from rosgate_testing import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "router.json5"
    config.write_text(json.dumps({"listen": {"endpoints": [endpoint]},
                                  "scouting": {"multicast": {"enabled": False}}}))
    router = subprocess.Popen([ROSGATE, "router", "--config", str(config)],
                              stderr=subprocess.PIPE, text=True)
    try:
        assert router.stderr is not None
        assert f"listening on what {config} says" in router.stderr.readline()
        client = zenoh.open(zenoh.Config.from_json5(json.dumps({
            "mode": "client", "connect": {"endpoints": [endpoint]},
            "scouting": {"multicast": {"enabled": False}}})))
        assert [str(z) for z in client.info.routers_zid()]  # a client opens only with a router
        client.close()
    finally:
        router.send_signal(signal.SIGINT)
        assert router.wait(10) == 0
    text = user_error(rosgate("router", "--listen", "tcp/127.0.0.1"))
    assert "zenoh router: " in text


def test_a_bus_without_name_templates_refuses_placeholders_at_the_entry_s_name():
    """Placeholders are the bus's to fill (zenoh's fleets); a bus that sets no ``templates``
    refuses them, located, and its entries without placeholders are keyed as on any bus."""
    from rosgate_fleet import FleetTransport

    class PlainBus(FleetTransport):
        name = "plainbus"

        def open(self, name):
            raise AssertionError("check opens nothing")

    plugins = Plugins.discover()
    module = types.ModuleType("rosgate_transport_plainbus")
    module.rosgate_transports = lambda register: register(PlainBus)  # type: ignore[attr-defined]
    plugins.add(module, "plainbus")
    assert plugins.failures == []
    head = "bridge: {name: r1, role: peer, defaults: {transport: plainbus}}\ntopics:\n"
    ok = Engine(loads(head + "  - {topic: /x, type: std_msgs/msg/String, direction: transmit}\n",
                      file="bringup.yaml"), plugins).prepare().plan
    assert [t.key for t in ok.topics] == ["rosgate/r1/x"]
    with pytest.raises(ConfigError) as info:
        Engine(loads(head + "  - {topic: '/{robot}/x', remote: 'f/{robot}/x', "
                            "type: std_msgs/msg/String, direction: receive}\n",
                     file="bringup.yaml"), plugins).prepare()
    e = info.value
    assert (e.file, e.line, e.key) == ("bringup.yaml", 3, "topics[0].topic"), str(e)
    assert e.message == "plainbus takes no placeholders such as {robot}"
    assert e.fix == "write the robot's name, or use a bus that takes them"


class Mqtt(BusTransport):
    """A bus transport written from outside, with a bus role of its own."""

    name = "mqtt"
    role = "mqttfleet"

    def open(self, name):
        raise AssertionError("the bus role opens what it needs")


class MqttRole(BusRole):
    """A bus role written from outside: keys of its own, and a record of what it was handed."""

    name = "mqttfleet"
    made: list[MqttRole] = []

    def __init__(self, bridge):
        super().__init__(bridge)
        self.wired: list[tuple[str, str | None]] = []
        MqttRole.made.append(self)

    @staticmethod
    def key(transport, entry, bridge):
        if entry.remote == "/refused":
            raise ConfigError("this bus refuses it", key="remote", fix="write another remote")
        return f"mqtt/{bridge}{entry.remote}"

    @staticmethod
    def speaks(transport, entry):
        return "mqtt's own"

    def topic(self, spec):
        self.wired.append(("topic", spec.key))

    def service(self, spec):
        self.wired.append(("service", spec.key))


def outside_plugins(*, with_role: bool) -> Plugins:
    """The built-ins and the mqtt transport, with or without its bus role: no rosgate-fleet."""
    plugins = Plugins()
    plugins.add(builtin, "builtin")
    module = types.ModuleType("rosgate_transport_mqtt")
    module.rosgate_transports = lambda register: register(Mqtt)  # type: ignore[attr-defined]
    if with_role:
        module.rosgate_bus_roles = lambda register: register(MqttRole)  # type: ignore[attr-defined]
    plugins.add(module, "mqtt")
    assert plugins.failures == []
    return plugins


MQTT = """\
bridge: {name: r1, role: peer, defaults: {transport: mqtt}}
topics:
  - {topic: /x, type: std_msgs/msg/String, direction: transmit}
"""


def test_a_bus_entry_whose_bus_role_is_not_installed_names_the_distribution_to_install():
    for role, distribution in [("mqttfleet", "by convention rosgate-bus_role-mqttfleet"),
                               ("fleet", "rosgate-fleet")]:
        Mqtt.role = role
        try:
            with pytest.raises(ConfigError) as info:
                Engine(loads(MQTT, file="bringup.yaml"),
                       outside_plugins(with_role=False)).prepare()
        finally:
            Mqtt.role = "mqttfleet"
        e = info.value
        assert (e.file, e.line, e.key) == ("bringup.yaml", 3, "topics[0].transport"), str(e)
        assert e.message == (f"mqtt is a bus, whose entries a bus role wires: unknown bus role "
                             f"{role!r} (installed bus roles: none)")
        assert e.fix == f"pip install the distribution that provides it ({distribution})"


def test_a_bus_role_from_outside_keys_and_wires_the_entries_of_its_bus(domain):
    """The hook the fleet role is registered through serves a third party alike: its keys reach
    the plan, its refusals are located at the entry's field, and one instance per bridge is
    handed every bus entry as the bridge starts."""
    plugins = outside_plugins(with_role=True)
    text = MQTT + ("services:\n"
                   "  - {service: /s, type: std_srvs/srv/Trigger, direction: receive}\n")
    with pytest.raises(ConfigError) as refused:  # a bus that does not judge its links is open
        Engine(loads(text, file="bringup.yaml"), plugins).prepare()
    assert (refused.value.line, refused.value.key) == (5, "services[0].transport")
    assert "/s: mqtt: mqtt does not say it authenticates" in refused.value.message
    text = text.replace("{transport: mqtt}", "{transport: mqtt}, insecure: true")
    engine = Engine(loads(text, file="bringup.yaml"), plugins, domain_id=domain())
    MqttRole.made.clear()
    engine.prepare()
    assert engine.plan is not None
    assert [t.key for t in engine.plan.topics] == ["mqtt/r1/x"]
    assert [s.key for s in engine.plan.services] == ["mqtt/r1/s"]
    assert MqttRole.made == []  # checking the file makes no role
    engine.start()
    try:
        assert len(MqttRole.made) == 1
        assert MqttRole.made[0].bridge.config.name == "r1"
        assert MqttRole.made[0].wired == [("topic", "mqtt/r1/x"), ("service", "mqtt/r1/s")]
    finally:
        engine.stop()
    with pytest.raises(ConfigError) as info:
        Engine(loads(MQTT.replace("direction: transmit}", "direction: transmit, "
                                  "remote: /refused}"), file="bringup.yaml"), plugins).prepare()
    e = info.value
    assert (e.file, e.line, e.key) == ("bringup.yaml", 3, "topics[0].remote"), str(e)
    assert (e.message, e.fix) == ("this bus refuses it", "write another remote")
