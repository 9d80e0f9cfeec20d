"""A bringup.yaml's entries, checked against what is installed, become a :class:`Plan` of
:class:`~rosgate.spec.RouteSpec` without opening anything (all ``rosgate check`` needs): its
main line, its listed entries, and the patterns that find names as they appear.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ..bus import BusTransport
from ..config import ActionConfig, BridgeConfig, Direction, Role, ServiceConfig, TopicConfig
from ..config.patterns import far_name, split
from ..spec import ServiceSpec, TopicSpec
from ..transport import Address, StreamTransport
from .entries import EntryResolver, PreparedAction
from .made import ErrorMaker


@dataclass
class Pattern:
    """A pattern entry of the file: it makes a route for each matching name that appears."""

    entry: TopicConfig | ServiceConfig | ActionConfig
    index: int  # its position in its section of the file
    section: str  # "topics" | "services" | "actions"
    checked: Any = None  # the spec of a stand-in name: its plugins are installed and fit

    @property
    def name(self) -> str:
        """The pattern as written (``/robot1/**``)."""
        return str(getattr(self.entry, _name_key(self.entry)))


#: a type every rclpy installation has, to check a pattern's plugins before any name is found
_STAND_IN = {"topics": "rcl_interfaces/msg/Log", "services": "rcl_interfaces/srv/ListParameters"}


def _name_key(entry: TopicConfig | ServiceConfig | ActionConfig) -> str:
    return ("topic" if isinstance(entry, TopicConfig) else "service"
            if isinstance(entry, ServiceConfig) else "action")


@dataclass
class Plan:
    """What a bridge will run: its prepared entries, and its main line (client and server)."""

    config: BridgeConfig
    topics: list[TopicSpec]
    services: list[ServiceSpec]
    main_line: StreamTransport | None = None
    main_address: Address | None = None
    actions: list[PreparedAction] = dataclasses.field(default_factory=list)
    patterns: list[Pattern] = dataclasses.field(default_factory=list)

    @property
    def action_parts(self) -> list[TopicSpec | ServiceSpec]:
        return [part for action in self.actions for part in action.parts]


class Resolver(EntryResolver):
    """Resolves entries against the installed plugins; plugin instances are made once per name."""

    def plan(self) -> Plan:
        cfg, main_line = self.config, None
        if cfg.role is not Role.PEER:
            main = self.transport(cfg.main_line, "bridge.main_line")
            if not isinstance(main, StreamTransport):
                raise cfg.error("bridge.main_line", f"{cfg.main_line!r} is not a stream transport",
                                "the main line needs a stream link such as tcp or bt")
            main_line = main
            try:
                self.main_address = main.check_address(main.parse_address(cfg.server or ""))
            except ValueError as exc:
                raise cfg.error("bridge.server", str(exc)) from None
        for key in ("transport", "codec", "cipher"):
            self.plugin(key, cfg.defaults[key], f"bridge.defaults.{key}")
        for name in cfg.links:
            if isinstance(self.transport(name, f"bridge.links.{name}"), BusTransport):
                raise cfg.error(f"bridge.links.{name}", f"{name} is a bus: it paces and orders "
                                "what it sends itself", f"remove {name} from bridge.links")
        if cfg.secure and cfg.role is Role.SERVER:
            for name, policy in cfg.clients.items():  # a cipher a rule names must exist
                for rule in [*policy.topics, *policy.services]:
                    for cipher in rule.ciphers or ():
                        self.plugin("cipher", cipher, f"clients.{name}")
        topics = [self.topic(t, i, "topics") for i, t in enumerate(cfg.topics) if not t.pattern]
        self._check_shared_ports(topics)
        services = [self.service(s, i, "services") for i, s in enumerate(cfg.services)
                    if not s.pattern]
        actions = [self.action(a, i, "actions") for i, a in enumerate(cfg.actions)
                   if not a.pattern]
        sections: list[tuple[str, list[Any]]] = [
            ("topics", cfg.topics), ("services", cfg.services), ("actions", cfg.actions)]
        for section, entries in sections:
            for i, entry in enumerate(entries):
                if entry.pattern:
                    self._can_find(entry, f"{section}[{i}]")
        patterns = [Pattern(entry, i, section, self.found(Pattern(entry, i, section), "/x", ""))
                    for section, entries in sections
                    for i, entry in enumerate(entries) if entry.pattern]
        if cfg.role is not Role.PEER and not cfg.secure and not cfg.insecure:
            key = "identity, server_key" if cfg.role is Role.CLIENT else "identity"
            raise cfg.error("bridge", f"a {cfg.role} needs bridge.{key} to authenticate its "
                            "sessions", "make one with 'rosgate keygen identity --out NAME.key' "
                            "(docs/security.md: setting up identities); or, on a network you "
                            "trust entirely, insecure: true")
        return Plan(cfg, topics, services, main_line, self.main_address, actions, patterns)

    def _can_find(self, entry: TopicConfig | ServiceConfig | ActionConfig, key: str) -> None:
        """What patterns find: a client's topics, services and actions, and a peer's topics and
        services, either way."""
        kind = _name_key(entry)
        if self.config.role is Role.PEER and self._bus_finds(entry, key):
            return
        if entry.framing.bare:  # not a bus's: a microcontroller's names are fixed
            raise self.config.error(f"{key}.framing", f"a pattern ({getattr(entry, kind)}) finds "
                                    f"ROS names as they appear; framing {entry.framing} sends a "
                                    "microcontroller's fixed names",
                                    "list each name as an entry of its own, or remove framing:")
        if self.config.role is Role.SERVER:
            raise self.config.error(f"{key}.{kind}", "a pattern is for a client's or a peer's "
                                    f"entries; a server lists each {kind} by its name",
                                    f"list each {kind} as an entry of its own")
        if self.config.role is Role.PEER and not isinstance(entry, ActionConfig):
            transport = self.transport(entry.transport, f"{key}.transport")
            if isinstance(transport, BusTransport) or (isinstance(transport, StreamTransport)
                                                       and isinstance(entry, ServiceConfig)):
                raise self.config.error(f"{key}.transport", f"a peer's {kind} pattern cannot "
                                        f"find names over {transport.name}",
                                        f"use udp{'' if kind == 'service' else ' or tcp'}, or "
                                        f"list each {kind} as an entry of its own")
        if self.config.role is Role.PEER and isinstance(entry, ActionConfig):
            raise self.config.error(f"{key}.{kind}", "a peer's pattern finds topics and "
                                    "services; a peer lists each action by its name",
                                    "list each action as an entry of its own")

    def _bus_finds(self, entry: TopicConfig | ServiceConfig | ActionConfig, key: str) -> bool:
        """Whether a peer's pattern entry is a receiving topic on a bus whose role finds the
        names announced on it (:attr:`rosgate.BusRole.finds`)."""
        if not (isinstance(entry, TopicConfig) and entry.direction is Direction.RECEIVE):
            return False
        transport = self.transport(entry.transport, f"{key}.transport")
        if not isinstance(transport, BusTransport):
            return False
        if not self.bus_role(transport, f"{key}.transport").finds(transport):
            raise self.config.error(f"{key}.topic", f"a pattern on {transport.name} takes the "
                                    f"topics announced there, and {transport.name} as set up "
                                    "here announces none this bridge can read",
                                    f"list each topic by its name, or see the {transport.name} "
                                    "plugin's documentation for the setting that reads the "
                                    "topics others announce")
        return True

    def found(self, pattern: Pattern, name: str, type_name: str,
              error: ErrorMaker | None = None) -> Any:
        """The spec of a name a pattern found (a topic's or service's spec, an action's parts),
        of ``type_name`` (the entry's own type when it gives one); with ``name`` a stand-in and
        no type, the pattern's plugins checked as a listed entry's are."""
        entry = pattern.entry
        written = getattr(entry, _name_key(entry))
        head = split(written)[0]
        if not (entry.type or type_name or pattern.section in _STAND_IN):
            # no type every installation has: the plugins' names are checked, the rest as found
            key = f"{pattern.section}[{pattern.index}]"
            self.transport(entry.transport, f"{key}.transport", error)
            for kind in ("codec", "cipher"):
                self.plugin(kind, getattr(entry, kind), f"{key}.{kind}", error)
            return None
        named: dict[str, Any] = {_name_key(entry): name if type_name else head + name}
        # framing none on a bus says no remote: the pattern's own names, as its keys are
        remote = entry.remote if "remote" in entry.lines else written
        concrete = dataclasses.replace(
            entry, **named,
            remote=far_name(written, remote, name) if type_name else head + name,
            type=entry.type or type_name or _STAND_IN[pattern.section])
        if isinstance(concrete, TopicConfig):
            return self.topic(concrete, pattern.index, pattern.section, error)
        if isinstance(concrete, ServiceConfig):
            return self.service(concrete, pattern.index, pattern.section, error)
        return self.action(concrete, pattern.index, pattern.section, error)
