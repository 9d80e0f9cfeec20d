"""The zenoh plugin: the kit's bus conformance suite through a zenoh router of the test's own,
and what is the plugin's own: options passed to zenoh, errors in zenoh's words, the router."""

from __future__ import annotations

import pytest
import zenoh
from rosgate_testing import BusConformance, free_port
from rosgate_transport_zenoh import ZenohTransport, zenoh_config
from rosgate_transport_zenoh.router import open_router

from rosgate import LinkError, OptionError

ROUTERS: list = []


@pytest.fixture(scope="module")
def router():
    """A zenoh router in this process, on a free loopback port, for the module's tests."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_router([endpoint], None)
    yield endpoint
    session.close()


class TestZenohConformance(BusConformance):
    transport = ZenohTransport

    @pytest.fixture
    def plugin(self, router):
        return ZenohTransport({"mode": "client", "connect": [router]})


def test_options_reach_zenoh_and_multicast_scouting_is_off_unless_asked():
    config = zenoh_config({"mode": "client", "connect": ["tcp/127.0.0.1:7447"],
                           "prefix": "fleet", "transport": {"link": {"tx": {"lease": 2000}}}})
    assert config.get_json("mode") == '"client"'
    assert config.get_json("connect/endpoints") == '["tcp/127.0.0.1:7447"]'
    assert config.get_json("transport/link/tx/lease") == "2000"
    assert config.get_json("scouting/multicast/enabled") == "false"
    asked = zenoh_config({"scouting": {"multicast": {"enabled": True}}})
    assert asked.get_json("scouting/multicast/enabled") == "true"


@pytest.mark.parametrize("options, key, words", [
    ({"mdoe": "client"}, "mdoe", "unknown key 'mdoe' (did you mean 'mode'?)"),
    ({"mode": "robot"}, "mode", "'robot' is not one of peer, client, router"),
    ({"connect": {"endpoints": "tcp/1.2.3.4:5"}}, "connect.endpoints",
     "expected list of endpoints"),
    ({"transport": {"link": {"tx": {"leese": 1}}}}, "transport.link.tx.leese",
     "unknown zenoh option 'leese' under transport.link.tx"),
    ({"scouting": {"multicast": {"enabled": "no"}}}, "scouting.multicast.enabled",
     "expected a boolean"),
    ({"prefix": "a//b"}, "prefix", "is not a key"),
    ({"prefix": 7}, "prefix", "expected a string, got 7"),
    ({"namespace": "/bot*"}, "namespace", "bot*"),
])
def test_a_wrong_option_names_itself(options, key, words):
    """The options rosgate declares are checked by rosgate; inside zenoh's sections, by zenoh,
    in its words, at the option's own path."""
    with pytest.raises(OptionError) as info:
        ZenohTransport(options)
    assert info.value.key == key
    assert words in info.value.message
    assert " at /" not in info.value.message  # no Rust source paths
    assert info.value.fix


def test_a_client_without_its_router_is_a_link_error():
    transport = ZenohTransport({"mode": "client", "connect": [f"tcp/127.0.0.1:{free_port()}"]})
    with pytest.raises(LinkError) as info:
        transport.open("lonely")
    assert "Unable to connect" in str(info.value)
    assert "mode: peer opens without one" in info.value.fix


def test_a_peer_opens_without_its_router():
    transport = ZenohTransport({"mode": "peer", "connect": [f"tcp/127.0.0.1:{free_port()}"]})
    transport.open("patient").close()


def test_keys_are_checked_as_zenoh_checks_them():
    transport = ZenohTransport({})
    assert transport.check_key("fleet/robot-1/scan") == "fleet/robot-1/scan"
    for bad in ("/scan", "scan/", "a//b", "a/b*c", ""):
        with pytest.raises(ValueError):
            transport.check_key(bad)


def test_reliable_topics_block_and_best_effort_ones_drop_at_their_priority(router):
    """What the bus promises per topic QoS, read back from the samples zenoh delivers."""
    transport = ZenohTransport({"mode": "client", "connect": [router]})
    a, b = transport.open("a"), transport.open("b")
    try:
        samples: list = []
        sub = b.session.declare_subscriber("qos/**", zenoh.handlers.Callback(
            samples.append, indirect=False))
        reliable = a.publisher("qos/reliable", reliable=True, priority=2)
        lossy = a.publisher("qos/lossy", reliable=False, priority=7)
        import time
        deadline = time.monotonic() + 5
        while len({str(s.key_expr) for s in samples}) < 2 and time.monotonic() < deadline:
            reliable.put(b"r")
            lossy.put(b"l")
            time.sleep(0.05)
        seen = {str(s.key_expr): (s.congestion_control, s.priority) for s in samples}
        assert seen == {
            "qos/reliable": (zenoh.CongestionControl.BLOCK, zenoh.Priority.INTERACTIVE_HIGH),
            "qos/lossy": (zenoh.CongestionControl.DROP, zenoh.Priority.BACKGROUND)}
        sub.undeclare()
    finally:
        a.close()
        b.close()
