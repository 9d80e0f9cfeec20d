"""The main line: the stream a client opens to its server, and what travels on it.

Control messages are frames on topic 0 with the CONTROL flag and a JSON body — JSON, not
pickle: a peer's bytes never become code. The client sends ``hello`` (its name, topics and
services); the server answers ``welcome`` (its name, a session id and token, one id per topic in
``topic_ids`` and one per service in ``service_ids``) or ``refused`` (why). Service calls then
travel as envelopes with the REQUEST / REPLY flags on the service's id (services.py has the
wire). Both sides send ``ping`` every ``heartbeat`` seconds. A client that stops cleanly sends
``bye``: the server drops its session at once.

A client also says hello on every datagram link and dedicated stream it uses (a HELLO-flagged
envelope with its session id and token), so the server learns where to send, even through NAT.

Authenticated sessions (:mod:`rosgate.secure`): every connection starts with the Noise handshake
and everything above travels inside it. The welcome then carries the session's secret
(``secret``, ``key_id``, ``rekey``) instead of a token, and ``refused``: the entries the
server's policy refused, each with the sentence both logs show (their ids are 0). The client
answers ``ready`` once it holds the new keys. Hellos on datagram links are sealed under the
session's keys (:func:`rosgate.secure.seal_hello`); on a dedicated stream the connection's own
handshake says whose it is.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from typing import Any

from ..actions import parts as action_parts
from ..config import (
    ActionConfig,
    ServiceConfig,
    TopicConfig,
    action_from_mapping,
    service_from_mapping,
    topic_from_mapping,
)
from ..errors import ConfigError
from ..wire import control as wire_control
from ..wire import envelope

PROTOCOL = 1           # main-line control protocol version
HANDSHAKE_TIMEOUT = 10.0


def control(message: dict[str, Any]) -> bytes:
    """A control frame for the main line: an envelope on topic 0 and a JSON body."""
    header = envelope.pack(envelope.FLAG_CONTROL, envelope.CONTROL_TOPIC, 0, 0, time.time_ns())
    return header + json.dumps(message, separators=(",", ":")).encode()


def is_control(frame: bytes) -> bool:
    return len(frame) > 3 and frame[:2] == envelope.MAGIC and bool(frame[3] & envelope.FLAG_CONTROL)


def parse_control(frame: bytes) -> dict[str, Any] | None:
    """A control frame's message, or None when it is none (bounded: :mod:`rosgate.wire.control`)."""
    try:
        message = wire_control.parse(frame[envelope.SIZE:])
    except wire_control.ControlError:
        return None
    return message if isinstance(message.get("type"), str) else None


def hello_datagram(session: int, token: bytes) -> bytes:
    """Sent by a client on each datagram link so the server learns the client's address there."""
    return envelope.pack(envelope.FLAG_HELLO, session, 0, 0, time.time_ns()) + token


def key_label(kind: str, way: str, name: str) -> str:
    """What a session's key of one entry and direction is derived for: ``topic c2s /robot1/scan``
    (``way``: c2s, client to server, or s2c; ``name``: the server's name of the entry)."""
    return f"{kind} {way} {name}"


def flipped(t: TopicConfig | ServiceConfig) -> Any:
    """The server's view of a client's topic or service: the other direction, names swapped."""
    name_key = "topic" if isinstance(t, TopicConfig) else "service"
    return replace(t, **{name_key: t.remote, "remote": getattr(t, name_key)},
                   direction=t.direction.flipped)


def where_error(where: str) -> Any:
    """An error maker for entries that came from a client (no file, no lines)."""
    def error(key: str, message: str, fix: str | None = None) -> ConfigError:
        return ConfigError(message, file=where, key=key, fix=fix)
    return error


def client_entries(hello: dict[str, Any], defaults: dict[str, str],
                   where: str) -> tuple[list[TopicConfig | ServiceConfig], dict[int, ActionConfig]]:
    """A hello's entries, checked like a file's (no type is imported here): topics, services,
    then the parts of its actions; and the action of each part."""
    error = where_error(where)
    topics, services = hello.get("topics"), hello.get("services", [])
    actions = hello.get("actions", [])
    if (not isinstance(topics, list) or not isinstance(services, list)
            or not isinstance(actions, list)):
        raise ConfigError("hello without a topic, a service and an action list", file=where)
    entries: list[TopicConfig | ServiceConfig] = []
    for key, items, parse in (("topics", topics, topic_from_mapping),
                              ("services", services, service_from_mapping)):
        for i, mapping in enumerate(items):
            if not isinstance(mapping, dict):
                raise error(f"{key}[{i}]", "not a mapping")
            entries.append(parse(mapping, defaults, where, index=i))
    part_of: dict[int, ActionConfig] = {}
    for i, mapping in enumerate(actions):
        if not isinstance(mapping, dict):
            raise error(f"actions[{i}]", "not a mapping")
        action = action_from_mapping(mapping, defaults, where, index=i)
        for part in action_parts(action):
            part_of[len(entries)] = action
            entries.append(part)
    return entries, part_of
