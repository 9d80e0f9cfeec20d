"""``clients:`` — the clients a server accepts, each with its public key and the rules of what
it may ask for (default deny), declared once as the bridge's keys are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..options import option, show
from . import kinds
from .kinds import Key

RULE_DIRECTIONS = ("transmit", "receive", "both")


@dataclass(frozen=True)
class Rule:
    """One rule of a client's policy (``clients.NAME.topics[i]`` / ``services[i]``): what it
    allows. ``None`` means any; names and types are globs (``*`` within a segment, ``**``
    across segments)."""

    name: str = option(doc="a glob on the server-side name: `*` and `?` within a segment, `**` "
                           "across", example="/robot1/**")
    direction: str = option(doc="the client's: `transmit` (it publishes or calls on the "
                                "server), `receive`, `both`", choices=RULE_DIRECTIONS,
                            example="transmit, receive or both")
    types: tuple[str, ...] | None = option(None, "globs on `pkg/msg/Type`", unset="any",
                                           example="[geometry_msgs/msg/*]", parse=kinds.names)
    ports: tuple[tuple[int, int], ...] = option(
        (), "ports of their own it may ask for", unset="none: the main port only",
        example="[12001, 12010-12019]", parse=kinds.port_ranges)
    ciphers: tuple[str, ...] | None = option(None, "ciphers it may use (`none` only when listed)",
                                             unset="any cipher a session keys", example="[aead]",
                                             parse=kinds.names)
    depth: int = option(1000, "topics: the deepest queue (QoS depth) an entry may ask for",
                        minimum=1, maximum=kinds.QOS_DEPTH_MAX, example="100")
    keep_all: bool = option(False, "topics: whether an entry may ask for history `keep_all` (a "
                            "queue without bound)", example="true")
    durability: tuple[str, ...] | None = option(None, "topics: the durabilities an entry may ask "
                                                "for", unset="any: `volatile`, `transient_local`",
                                                example="[volatile]", parse=kinds.durabilities)
    shared: bool = option(False, "actions: whether the client sees and may cancel every goal of "
                          "the action, other clients' too (else only the goals it sent)",
                          example="true")
    line: int = 0


def _rules(key: Key, value: Any) -> tuple[Rule, ...]:
    """a list of rules: `- {name: /robot1/**, direction: both}`"""
    fix = "e.g. - {name: /robot1/**, direction: both}"
    if value is None:  # written empty
        return ()
    if not isinstance(value, list):
        raise key.error(f"expected a list of rules, got {show(value)}", fix=fix)
    return tuple(kinds.item(key.src, f"{key.path}[{i}]", rule, Rule,
                            "a rule (name:, direction: ...)", fix) for i, rule in enumerate(value))


@dataclass(frozen=True)
class ClientPolicy:
    """A client a server accepts: its public key and what it may ask for (default deny)."""

    name: str
    key: bytes = option(doc="the client's public key; `NAME` is its `bridge.name`",
                        example="<the client's public key>", parse=kinds.public_key)
    topics: tuple[Rule, ...] = option((), "rules: topics the client may bridge; an entry must "
                                      "match one", unset="none: every topic refused", parse=_rules)
    services: tuple[Rule, ...] = option((), "rules: services the client may bridge",
                                        unset="none", parse=_rules)
    actions: tuple[Rule, ...] = option((), "rules: actions the client may bridge", unset="none",
                                       parse=_rules)
    line: int = 0

