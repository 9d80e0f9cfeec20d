"""The main line: the stream a client opens to its server, and what travels on it.

Control messages are frames on topic 0 with the CONTROL flag and a JSON body — JSON, not
pickle: a peer's bytes never become code. The client sends ``hello`` (its name and topics); the
server answers ``welcome`` (its name, a session id and token, one topic id per topic) or
``refused`` (why). Both sides send ``ping`` every ``heartbeat`` seconds. A client that stops
cleanly sends ``bye``: the server drops its session at once.

A client also says hello on every datagram link and dedicated stream it uses (a HELLO-flagged
envelope with its session id and token), so the server learns where to send, even through NAT.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from typing import Any

from . import envelope
from .config import TopicConfig

PROTOCOL = 1           # main-line control protocol version
HANDSHAKE_TIMEOUT = 10.0


def control(message: dict[str, Any]) -> bytes:
    """A control frame for the main line: an envelope on topic 0 and a JSON body."""
    header = envelope.pack(envelope.FLAG_CONTROL, envelope.CONTROL_TOPIC, 0, 0, time.time_ns())
    return header + json.dumps(message, separators=(",", ":")).encode()


def parse_control(frame: bytes) -> dict[str, Any] | None:
    try:
        message = json.loads(frame[envelope.SIZE:])
    except (ValueError, UnicodeDecodeError):
        return None
    return message if isinstance(message, dict) and isinstance(message.get("type"), str) else None


def hello_datagram(session: int, token: bytes) -> bytes:
    """Sent by a client on each datagram link so the server learns the client's address there."""
    return envelope.pack(envelope.FLAG_HELLO, session, 0, 0, time.time_ns()) + token


def flipped(t: TopicConfig) -> TopicConfig:
    """The server's view of a client's topic: the other direction, names swapped."""
    return replace(t, topic=t.remote, remote=t.topic,
                   direction="receive" if t.direction == "transmit" else "transmit")
