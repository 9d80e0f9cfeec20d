"""Every interface arrives exact: ROS's own test set (``test_msgs``), filled with values at the
edges of every field kind (tests/interfaces.py), through every codec installed in the tree —
first codec to codec in this process, then through a pair of bridges and compared field by field
after the far publish."""

from __future__ import annotations

import time
from functools import partial

import pytest
from conftest import free_port
from interfaces import corpus, differences
from rclpy.serialization import deserialize_message, serialize_message

from rosgate.plugins import Plugins

PLUGINS = Plugins.discover()
CODECS = PLUGINS.names("codec")
CORPUS = list(corpus())


def through(codec_name: str, message: object) -> object:
    cls = PLUGINS.get("codec", codec_name).cls
    codec = cls(type(message), {})
    if cls.raw:
        data = codec.decode(codec.encode(serialize_message(message)))
        return deserialize_message(data, type(message))
    return codec.decode(codec.encode(message))


def test_the_corpus_covers_every_test_msgs_type_and_the_codecs_of_the_tree():
    assert len({name for name, _, _ in CORPUS}) == 13
    assert {"cdr", "msgpack", "cbor"} <= set(CODECS)


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize("name,variant,message", CORPUS, ids=[f"{n.split('/')[-1]}-{v}"
                                                               for n, v, _ in CORPUS])
def test_codec_carries_the_message_exactly(codec, name, variant, message):
    arrived = through(codec, message)
    assert differences(message, arrived) == []


@pytest.mark.parametrize("codec", CODECS)
def test_every_interface_crosses_a_bridge_exactly(codec, engines, domain, ros_side):
    """Each type on a topic of its own, published on one side and compared field by field with
    what the far side's bridge published."""
    classes = {name: type(message) for name, _, message in CORPUS}
    da, db = domain(), domain()
    entries = [(f"/{name.split('/')[-1].lower()}", name, free_port()) for name in classes]
    topics = lambda direction: "\n".join(
        f"  - {{topic: {topic}, type: {name}, direction: {direction}, port: {port}, "
        f"codec: {codec}}}" for topic, name, port in entries)
    engines(f"bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}\n"
            f"topics:\n{topics('transmit')}", da)
    engines(f"bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}\n"
            f"topics:\n{topics('receive')}", db)
    talker, listener = ros_side(da, "talker"), ros_side(db, "listener")
    for topic, name, _ in entries:
        sent = {variant: message for n, variant, message in CORPUS if n == name}
        inbox = listener.listen(topic, classes[name])
        publisher = talker.publisher(topic, classes[name])
        # "low" until one crosses (discovery takes a moment), then the other two once each
        deadline = time.monotonic() + 20
        while not inbox.wait_count(1, 0.2):
            assert time.monotonic() < deadline, f"{name}: nothing crossed"
            publisher.publish(sent["low"])
        assert differences(sent["low"], inbox.items[0]) == []
        for variant in ("high", "special"):
            publisher.publish(sent[variant])
        arrived = partial(_has, sent["special"])
        assert inbox.wait_for(arrived, 10), f"{name}: not all arrived"
        for variant in ("high", "special"):
            assert any(not differences(sent[variant], m) for m in inbox.items), \
                (name, variant, [differences(sent[variant], m) for m in inbox.items])


def _has(message: object, items: list) -> bool:
    return len(items) >= 3 and any(not differences(message, m) for m in items)
