"""The main line: the stream a client opens to its server, and its control messages — frames on
topic 0 with the CONTROL flag and a JSON body (never pickle: a peer's bytes never become code).

The client sends ``hello`` (name, topics, services, actions, and the names its patterns
found: ``found``, an action among them taking the places of its five parts); the server
answers ``welcome`` (its name, a session id and token, ``topic_ids`` and ``service_ids`` in
the order asked, 0 for an entry its policy ``refused``, with why) or ``refused`` (why). Both
``ping`` every ``heartbeat``;
a client that stops cleanly says ``bye`` and the server drops its session at once; a server that
stops says ``bye`` to each client, whose reliable topics then wait for the next session. On each
datagram link and dedicated stream the client also sends a HELLO-flagged envelope (session id,
token) so the server learns where to send, even through NAT.

Each hello says what the client took (``taken``) of each topic it receives (the newest sequence
number per epoch); a welcome to a session the server kept says the same of the server's. Each
side then writes again what the other did not get of what its last connection carried
(:class:`~rosgate.streamlink.slot.LinkSlot`): a connection dies with what its buffers held.

Authenticated (:mod:`rosgate.secure`): all of it travels inside the Noise handshake; the welcome
carries the session's secret (``secret``, ``key_id``, ``rekey``) too, the client answers
``ready`` once it holds it, and datagram hellos are sealed under the session's keys (the token
then only tells a restarted server's session from the one the client had).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable
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
from ..routes import ReceiveRoute, Route
from ..streamlink.slot import Taken
from ..wire import control as wire_control
from ..wire import envelope

PROTOCOL = 1  # main-line control protocol version
HANDSHAKE_TIMEOUT = 10.0


def control(message: dict[str, Any]) -> bytes:
    header = envelope.pack(envelope.FLAG_CONTROL, envelope.CONTROL_TOPIC, 0, 0, time.time_ns())
    return header + json.dumps(message, separators=(",", ":")).encode()


def parse_control(frame: bytes) -> dict[str, Any] | None:
    """A control frame's message, or None when it is none (bounded: :mod:`rosgate.wire.control`)."""
    try:
        message = wire_control.parse(frame[envelope.SIZE:])
    except wire_control.ControlError:
        return None
    return message if isinstance(message.get("type"), str) else None


def hello_datagram(session: int, token: bytes) -> bytes:
    return envelope.pack(envelope.FLAG_HELLO, session, 0, 0, time.time_ns()) + token


def taken(routes: Iterable[Route]) -> list[list[Any]]:
    """What the receiving ``routes`` took, as a hello or a welcome says it."""
    return [[r.topic_id, [[epoch, seq] for epoch, seq in r.taken().items()]]
            for r in routes if isinstance(r, ReceiveRoute)]


def read_taken(said: Any) -> Taken | None:
    """What the far side says it took (:func:`taken`); None when it says nothing readable."""
    if not isinstance(said, list):
        return None
    try:
        return {int(topic_id): {int(epoch): int(seq) for epoch, seq in newest}
                for topic_id, newest in said}
    except (TypeError, ValueError, OverflowError):  # OverflowError: an infinite number
        return None


def key_label(kind: str, way: str, name: str) -> str:
    """What a session's key of one entry and way is derived for: ``topic c2s /robot1/scan``."""
    return f"{kind} {way} {name}"


def flipped(t: TopicConfig | ServiceConfig) -> Any:
    """The server's view of a client's entry: the other direction, names swapped."""
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
    lists = [hello.get("topics"), hello.get("services", []), hello.get("actions", [])]
    if not all(isinstance(items, list) for items in lists):
        raise ConfigError("hello without a topic, a service and an action list", file=where)
    entries: list[TopicConfig | ServiceConfig] = []
    part_of: dict[int, ActionConfig] = {}
    parsers: list[Callable[..., TopicConfig | ServiceConfig | ActionConfig]] = [
        topic_from_mapping, service_from_mapping, action_from_mapping]
    for key, items, parse in zip(("topics", "services", "actions"), lists, parsers, strict=True):
        for i, mapping in enumerate(items):
            if not isinstance(mapping, dict):
                raise ConfigError("not a mapping", file=where, key=f"{key}[{i}]")
            entry = parse(mapping, defaults, where, index=i)
            if not isinstance(entry, ActionConfig):
                entries.append(entry)
                continue
            for part in action_parts(entry):
                part_of[len(entries)] = entry
                entries.append(part)
    return entries, part_of


MAX_FOUND = 10_000  # names a client's patterns may have found, gone ones included


def found_entries(hello: dict[str, Any], defaults: dict[str, str], where: str
                  ) -> tuple[list[TopicConfig | ServiceConfig | None], dict[int, ActionConfig]]:
    """The topics, services and actions a client's pattern entries found (``found``, after its
    listed entries; None for a name that went), each checked like a listed entry: an action as
    its parts, in their places; and the action of each part, by its place among them."""
    items = hello.get("found", [])
    if not isinstance(items, list) or len(items) > MAX_FOUND:
        raise ConfigError(f"found: not a list of at most {MAX_FOUND} entries", file=where)
    found: list[TopicConfig | ServiceConfig | None] = []
    part_of: dict[int, ActionConfig] = {}
    for i, mapping in enumerate(items):
        if mapping is not None and not isinstance(mapping, dict):
            raise ConfigError("not a mapping", file=where, key=f"found[{i}]")
        if mapping is None:
            found.append(None)
        elif "action" in mapping:
            action = action_from_mapping(mapping, defaults, where, index=i)
            for part in action_parts(action):
                part_of[len(found)] = action
                found.append(part)
        else:
            parse = service_from_mapping if "service" in mapping else topic_from_mapping
            found.append(parse(mapping, defaults, where, index=i))
    return found, part_of
