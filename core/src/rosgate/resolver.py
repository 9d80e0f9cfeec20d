"""A bringup.yaml's entries, checked against what is installed, become a :class:`Plan` of
:class:`~rosgate.spec.RouteSpec` without opening anything (all ``rosgate check`` needs); a server
resolves a client's hello the same way, with an error maker that names the client.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from . import actions
from .bus import BusRole, BusTransport
from .cipher import Cipher
from .codec import Codec
from .config import (
    NO_PLUGIN,
    PRIORITIES,
    ActionConfig,
    BridgeConfig,
    Direction,
    Framing,
    Role,
    ServiceConfig,
    TopicConfig,
)
from .config.patterns import far_name, split
from .errors import ConfigError, OptionError
from .options import parse
from .packetizer import SMALL_FRAME, Packetizer, own_packetizer
from .plugins import Plugins, Registration
from .ros import TypeNotFound, is_reliable, resolve_type
from .service_framing import ServiceFraming
from .spec import Delivery, ServiceSpec, TopicSpec
from .transform import Transform
from .transport import Address, DatagramTransport, StreamTransport, Transport
from .wire.envelope import topic_id_for
from .wire.framing import DEFAULT_MAX_MESSAGE

ErrorMaker = Callable[..., ConfigError]
log = logging.getLogger("rosgate")

#: the packetizer that repairs a reliable topic on a datagram link when it sets no recovery:
#: selective repeat costs a round trip per loss and bandwidth only for what was lost, keeps the
#: topic on the link the file chose (no head-of-line wait behind other topics, as on the main
#: line's stream) and is the far side's to answer without a setting
RELIABLE_RECOVERY = "retransmit"

ANY_IP = "0.0.0.0"
NO_ADDRESS: Address = ("", 0)  # bus entries have a key instead


@dataclass
class PreparedAction:
    """An action as the five entries it is made of (rosgate.actions), each prepared."""

    config: ActionConfig
    parts: list[TopicSpec | ServiceSpec]


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


class Resolver:
    """Resolves entries against the installed plugins; plugin instances are made once per name."""

    def __init__(self, config: BridgeConfig, plugins: Plugins):
        self.config = config
        self.plugins = plugins
        self.transports: dict[str, Transport] = {}
        self.ciphers: dict[str, Cipher] = {}
        self.main_address: Address | None = None
        self._decoders: dict[int, Transform | None] = {}
        self._decoders_lock = threading.Lock()
        #: what entries give up, said once each (a reliable topic carried unrepaired)
        self.cautions: list[str] = []

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

    # -- entries ---------------------------------------------------------------------------
    def topic(self, topic: TopicConfig, index: int, section: str,
              error: ErrorMaker | None = None) -> TopicSpec:
        error = error or self.config.error
        key = f"{section}[{index}]"
        transport, common = self._entry(topic, index, key, error)
        if topic.framing is Framing.NONE and isinstance(transport, StreamTransport):
            raise error(f"{key}.framing",
                        "framing: none needs a datagram transport (udp, can, ...)",
                        "use framing: rosgate on stream links")
        delivery = self._delivery(topic, key, transport, error)
        compression = None if topic.compression == NO_PLUGIN else self._made(
            "transform", topic.compression, f"{key}.compression", error, DEFAULT_MAX_MESSAGE,
            own=topic.compression_options)
        return TopicSpec(**common, **self._where(topic, key, transport, error),
                         delivery=delivery, compression=compression,
                         transforms=self.transform_for)

    def _entry(self, entry: TopicConfig | ServiceConfig, index: int, key: str,
               error: ErrorMaker) -> tuple[Transport, dict[str, Any]]:
        """An entry's transport, and what its spec holds of every plugin and of its type, each
        checked: its codec's options fit the type (a service's Request and Response)."""
        transport = self.transport(entry.transport, f"{key}.transport", error)
        if isinstance(transport, DatagramTransport) and entry.framing is Framing.ROSGATE:
            name = own_packetizer(transport.max_frame)  # a link of small frames needs a plugin's
            if self.plugins.get("packetizer", name) is None:
                message, fix = self.plugins.explain_missing("packetizer", name, False)
                raise error(f"{key}.transport", f"{transport.name} carries packets of "
                            f"{transport.max_frame} bytes, which its links cut with the "
                            f"packetizer {name!r}: {message}", fix)
        # the codec's options are parsed once; the router makes an instance per route
        codec_cls: type[Codec] = self.plugin("codec", entry.codec, f"{key}.codec", error).cls
        codec_options = _microcontroller(codec_cls, self._plugin_options(
            codec_cls, entry.codec, {}, f"{key}.codec", error), entry)
        cipher_cls, cipher = self._entry_cipher(entry.cipher, f"{key}.cipher", error,
                                                isinstance(transport, BusTransport))
        try:
            interface: Any = resolve_type(entry.type)
        except TypeNotFound as exc:
            raise error(f"{key}.type", str(exc)) from None
        topic = isinstance(entry, TopicConfig)
        try:
            for part in (interface,) if topic else (interface.Request, interface.Response):
                codec_cls(part, codec_options)
        except OptionError as exc:
            raise self.option_error(entry.codec, exc, f"{key}.codec", error) from None
        return transport, {"config": entry, "msg_type" if topic else "srv_type": interface,
                           "codec_cls": codec_cls, "codec_options": codec_options,
                           "transport": transport, "cipher": cipher, "cipher_cls": cipher_cls,
                           "index": index}

    def _where(self, entry: TopicConfig | ServiceConfig, key: str, transport: Transport,
               error: ErrorMaker) -> dict[str, Any]:
        """Where an entry's frames go: its key on a bus, else its addresses."""
        if isinstance(transport, BusTransport):
            return {"address": NO_ADDRESS, "local": NO_ADDRESS,
                    "key": self._bus_key(transport, entry, key, error)}
        self._point_to_point(entry, key, transport, error)
        address, local = self._addresses(transport, entry, key, error)
        return {"address": address, "local": local}

    def _delivery(self, topic: TopicConfig, key: str, transport: Transport,
                  error: ErrorMaker) -> Delivery:
        """Recovery is for datagram links, latest_only for the links rosgate schedules (a bus
        paces and drops by itself)."""
        bus = isinstance(transport, BusTransport)
        if topic.recovery not in (None, NO_PLUGIN) and (isinstance(transport, StreamTransport)
                                                         or bus):
            what = "a bus" if bus else "a stream"
            raise error(f"{key}.recovery", f"recovery: {topic.recovery} is for datagram links "
                        f"(udp): {topic.transport} is {what}, which delivers whole and in order "
                        "by itself", "remove recovery: from this entry")
        if topic.latest_only is not None and bus:
            raise error(f"{key}.latest_only", f"latest_only applies to links rosgate schedules; "
                        f"{topic.transport} is a bus, which drops best-effort samples itself "
                        "when it is congested", "remove latest_only: from this entry")
        reliable, priority = is_reliable(topic.qos), topic.priority or PRIORITIES["data"]
        if bus:
            return Delivery(reliable=reliable, priority=priority)
        packetizer: type[Packetizer] | None = None
        options = None
        recovery = self._recovery(topic, key, reliable, transport)
        if recovery != NO_PLUGIN:
            packetizer = self.plugin("packetizer", recovery, f"{key}.recovery", error).cls
            if packetizer.cuts_every_frame:
                raise error(f"{key}.recovery", f"{recovery} is what links of small frames "
                            "cut every frame with, by themselves: it recovers nothing",
                            "remove recovery: from this entry, or pick fec or retransmit")
            small = transport.max_frame if isinstance(transport, DatagramTransport) else 0
            if 0 < small < SMALL_FRAME:  # its own packetizer cuts every frame: none else would
                raise error(f"{key}.recovery", f"{topic.transport} carries frames of {small} "
                            "bytes, which it cuts into compact pieces with no room for "
                            f"{recovery}'s numbers: it would recover nothing",
                            f"give {topic.transport} a max_frame of {SMALL_FRAME} or more, or "
                            "remove recovery: from this entry")
            options = self._plugin_options(packetizer, recovery, topic.recovery_options,
                                           f"{key}.recovery", error)
        latest_only = not reliable if topic.latest_only is None else topic.latest_only
        return Delivery(reliable=reliable, priority=priority, latest_only=latest_only,
                        max_delay=topic.max_delay, packetizer=packetizer,
                        packetizer_options=options, whole=topic.framing is Framing.NONE)

    def _recovery(self, topic: TopicConfig, key: str, reliable: bool,
                  transport: Transport) -> str:
        """A datagram topic's recovery: its own, else by its QoS (a reliable topic is repaired,
        in order, by :data:`RELIABLE_RECOVERY`; a best-effort one stays fresh). What a reliable
        topic gives up without it is said (:attr:`cautions`)."""
        # a link of small frames (CAN) repairs in its hardware, and has no room for the header
        repairable = (isinstance(transport, DatagramTransport) and topic.framing is Framing.ROSGATE
                      and transport.max_frame >= SMALL_FRAME)
        if not (repairable and reliable):
            return topic.recovery or NO_PLUGIN
        name = f"{topic.topic} ({key})"
        if topic.recovery == NO_PLUGIN:
            self.caution(f"{name}: reliable QoS on {topic.transport} with recovery: none: a "
                         "datagram lost on the way loses its message (counted as lost on the "
                         "way by the receiver), and messages may be published out of order. "
                         "Leave recovery: out to have them repaired (retransmit)")
        if topic.recovery is not None:
            return topic.recovery
        if self.plugins.get("packetizer", RELIABLE_RECOVERY) is None:
            message, fix = self.plugins.explain_missing("packetizer", RELIABLE_RECOVERY, False)
            self.caution(f"{name}: reliable QoS on {topic.transport}, where the packetizer "
                         f"{RELIABLE_RECOVERY!r} would repair what is lost on the way; it is not "
                         f"here ({message}), so a lost datagram loses its message. {fix}; or "
                         "set recovery: none to accept it")
            return NO_PLUGIN
        return RELIABLE_RECOVERY

    def caution(self, text: str) -> None:
        """Say once, as a warning, what an entry gives up (``rosgate check`` and ``run``)."""
        if text not in self.cautions:
            self.cautions.append(text)
            log.warning("%s", text)

    def _plugin_options(self, cls: type, name: str, own: dict[str, Any], asked_by: str,
                        error: ErrorMaker) -> Any:
        """Its ``plugins:`` table, with what an entry gives (``compression: {zstd: {level: 19}}``)
        over it; a mistake is located where it was written."""
        try:
            return parse(cls, {**self._options(name), **own}, self.config.base_dir)
        except OptionError as exc:
            if exc.key is not None and exc.key in own:
                raise error(f"{asked_by}.{name}.{exc.key}", exc.message, exc.fix) from None
            raise self.option_error(name, exc, asked_by, error) from None

    def transform_for(self, wire_id: int) -> Transform | None:
        """The transform a receiver decodes a payload of ``wire_id`` with (options from this
        file's ``plugins:`` table), made once; None when no installed transform has that id."""
        with self._decoders_lock:
            if wire_id not in self._decoders:
                self._decoders[wire_id] = None
                found = self.plugins.by_wire("transform", wire_id)
                if found is not None:
                    with contextlib.suppress(OptionError):  # check reports it; frames are counted
                        options = parse(found.cls, self._options(found.name), self.config.base_dir)
                        self._decoders[wire_id] = found.cls(options, DEFAULT_MAX_MESSAGE)
            return self._decoders[wire_id]

    def service(self, service: ServiceConfig, index: int, section: str,
                error: ErrorMaker | None = None) -> ServiceSpec:
        error = error or self.config.error
        key = f"{section}[{index}]"
        transport, common = self._entry(service, index, key, error)
        service_framing: type[ServiceFraming] | None = None
        if service.framing is not Framing.ROSGATE:  # a microcontroller's calls: by a plugin
            service_framing = self.plugin("service_framing", service.framing.value,
                                          f"{key}.framing", error).cls
            if self.config.role is not Role.PEER:
                raise error(f"{key}.framing", f"framing {service.framing} is for microcontroller "
                            "peers, which have no main line", "use role: peer for this bridge")
            on_a_line = isinstance(transport, DatagramTransport) and transport.one_line
            if not isinstance(transport, StreamTransport) and not (
                    on_a_line and service_framing.on_a_line):
                raise error(f"{key}.transport", f"framing {service.framing} needs a stream "
                            "transport (one connection per call)", "use transport: tcp")
            if not common["codec_cls"].messagepack:
                raise error(f"{key}.codec", f"codec {service.codec} does not put the service's "
                            "name on the wire (it does not write MessagePack)",
                            "use codec: msgpack")
        return ServiceSpec(**common, **self._where(service, key, transport, error),
                           service_framing=service_framing)

    def action(self, action: ActionConfig, index: int, section: str,
               error: ErrorMaker | None = None) -> PreparedAction:
        """An action's five entries, prepared as topics and services are; a mistake is
        located at the action's keys."""
        error = error or self.config.error
        key = f"{section}[{index}]"
        try:
            resolve_type(action.type)
        except TypeNotFound as exc:
            raise error(f"{key}.type", str(exc)) from None
        bus = isinstance(self.transport(action.transport, f"{key}.transport", error),
                         BusTransport)
        if self.config.role is Role.PEER and action.port is None and not bus:
            raise error(f"{key}.port", "peer role: an action needs a port (its calls use it, "
                        "its feedback and status the next one)", "add port: <1..65534>")
        return PreparedAction(action, [
            self.topic(part, index, section, error) if isinstance(part, TopicConfig)
            else self.service(part, index, section, error) for part in actions.parts(action)])

    def _bus_key(self, transport: BusTransport, entry: TopicConfig | ServiceConfig, key: str,
                 error: ErrorMaker) -> str:
        """A bus entry's key, as its bus role makes it. Bus entries live in peer-role files (no
        main line: the bus finds the others) and have no port."""
        kind, cfg = _kind(entry), self.config
        if cfg.role is not Role.PEER:
            raise error(f"{key}.transport", f"{entry.transport} is a bus: its {kind}s belong in a "
                        f"file of role peer (no main line: {entry.transport} finds the others)",
                        f"use role: peer for this bridge, or another transport for this {kind}")
        if entry.port is not None:
            raise error(f"{key}.port", f"port: does not apply to a {entry.transport} {kind}: "
                        "it is published on a key (remote:)", "remove port: from this entry")
        role = self.bus_role(transport, f"{key}.transport", error)
        try:
            return role.key(transport, entry, cfg.name)
        except ConfigError as exc:
            raise error(f"{key}.{exc.key}", exc.message, exc.fix) from None

    def bus_role(self, transport: BusTransport, key: str,
                 error: ErrorMaker | None = None) -> type[BusRole]:
        """The bus role that wires ``transport``'s entries; a :class:`ConfigError` at ``key``
        naming the distribution to install when it is not here."""
        found = self.plugins.get("bus_role", transport.role)
        if found is None:
            message, fix = self.plugins.explain_missing("bus_role", transport.role)
            raise (error or self.config.error)(
                key, f"{transport.name} is a bus, whose entries a bus role wires: {message}", fix)
        return found.cls

    def _point_to_point(self, entry: TopicConfig | ServiceConfig, key: str, transport: Transport,
                        error: ErrorMaker) -> None:
        """What only a bus takes: placeholders, a key for remote; and what point-to-point
        entries need: a port (a peer's; a client's off the main line), peer: for the far host."""
        cfg, kind = self.config, _kind(entry)
        name = entry.topic if isinstance(entry, TopicConfig) else entry.service
        if "{" in name or "}" in name:
            raise error(f"{key}.{kind}", f"placeholders such as {{robot}} need a bus transport "
                        f"(zenoh); {entry.transport} links one peer to another",
                        "set transport: zenoh on this entry, or write the robot's name")
        if entry.framing is Framing.ROSGATE and not entry.remote.startswith("/"):
            raise error(f"{key}.remote", f"'{entry.remote}' is not a valid ROS name (keys are "
                        f"for bus transports; {entry.transport} is not one)",
                        "use letters, digits and '_' in parts separated by single '/'")
        if cfg.role is Role.PEER:
            if entry.port is None:
                raise error(f"{key}.port", f"peer role: each {kind} needs its own port",
                            f"add port: <1..65535> to this entry (only bus {kind}s, such as "
                            "zenoh's, have none)")
            if cfg.peer is None:
                raise cfg.error("bridge.peer", "missing required key 'peer'",
                                f"add peer: <far host>, the address of the other side "
                                f"({key} is on {entry.transport}, a point-to-point link)")
        if (cfg.role is Role.CLIENT and isinstance(transport, StreamTransport)
                and entry.port is None and entry.transport != cfg.main_line):
            raise error(f"{key}.port", f"a {kind} on {entry.transport} needs a port of its own "
                        f"(only {cfg.main_line} {kind}s ride the main line)", "add port: <number>")

    def _addresses(self, transport: Transport, entry: TopicConfig | ServiceConfig, key: str,
                   error: ErrorMaker) -> tuple[Address, Address]:
        """(the entry's address, the local address a peer sends from), from the bridge's hosts
        and the entry's port, as its transport accepts them (an RFCOMM channel is not any port).

        Client and server: the server's host and the entry's port (default: the main port).
        Peer: a receiving entry listens at ``listen:port``, a transmitting one sends to
        ``peer:port`` from ``listen`` (any port)."""
        cfg = self.config
        if cfg.role is Role.PEER:
            listen = cfg.listen or ANY_IP
            receive = entry.direction is Direction.RECEIVE
            host = listen if receive else cfg.peer
            where = "bridge.listen" if receive else "bridge.peer"
            local = (listen, 0)
            if not receive and isinstance(transport, DatagramTransport):  # a sender binds too
                local = self._check(transport, local, "bridge.listen", error,
                                    f"set bridge.listen to this side's {entry.transport} address")
        else:
            assert self.main_address is not None
            host, where = self.main_address[0], "bridge.server"
            local = ("::" if ":" in host else ANY_IP, 0)
        port = entry.port or (self.main_address[1] if self.main_address else 0)
        fix = f"this {_kind(entry)}'s {entry.transport} address is {where} with port {port}"
        if where == "bridge.listen" and "bridge.listen" not in cfg.lines:  # 0.0.0.0: IP only
            fix = f"set bridge.listen to this side's {entry.transport} address"
        return self._check(transport, (host or "", port), f"{key}.port" if entry.port else where,
                           error, fix), local

    @staticmethod
    def _check(transport: Transport, address: Address, key: str, error: ErrorMaker,
               fix: str) -> Address:
        try:
            return transport.check_address(address)
        except ValueError as exc:
            raise error(key, str(exc), fix) from None

    def _check_shared_ports(self, topics: list[TopicSpec]) -> None:
        """Topics that share a receiving port must be told apart on it."""
        by_port: dict[tuple[str, int | None], list[TopicSpec]] = {}
        topics = [p for p in topics if p.key is None]  # a bus tells topics apart by key
        for p in topics:
            if p.config.direction is Direction.RECEIVE:
                by_port.setdefault((p.config.transport, p.config.port), []).append(p)
        for group in by_port.values():
            bare = [p for p in group if p.config.framing is Framing.NONE]
            if bare and len(bare) != len(group):
                raise self.config.error(f"topics[{bare[0].index}].framing",
                                        "topics on one port must all use the same framing")
            if len(bare) > 1 and not all(p.codec_cls.messagepack for p in bare):
                p = next(p for p in bare if not p.codec_cls.messagepack)
                raise self.config.error(
                    f"topics[{p.index}].port", f"codec {p.config.codec} does not name its frames, "
                    "so with framing: none this topic needs a port of its own",
                    "give each such topic its own port, or use codec msgpack")
        if self.config.role is Role.PEER:
            seen: dict[int, TopicSpec] = {}
            for p in topics:
                t = p.config
                for name in ({t.topic, t.remote} if t.direction is Direction.RECEIVE
                             else {t.remote}):
                    other = seen.setdefault(topic_id_for(name), p)
                    if other is not p and other.config.direction == t.direction:
                        raise self.config.error(
                            f"topics[{p.index}].remote",
                            f"link name {name!r} collides with topics[{other.index}]",
                            "rename one of them (remote: ...)")

    # -- plugins ---------------------------------------------------------------------------
    def plugin(self, kind: str, name: str, key: str,
               error: ErrorMaker | None = None) -> Registration:
        registration = self.plugins.get(kind, name)
        if registration is None:
            message, fix = self.plugins.explain_missing(kind, name)
            raise (error or self.config.error)(key, message, fix)
        return registration

    def transport(self, name: str, key: str, error: ErrorMaker | None = None) -> Transport:
        if name not in self.transports:
            self.transports[name] = self._made("transport", name, key, error)
        return self.transports[name]

    def _made(self, kind: str, name: str, key: str, error: ErrorMaker | None, *args: Any,
              own: dict[str, Any] | None = None) -> Any:
        """A plugin made with its options from the file and ``own`` (and ``args``)."""
        cls = self.plugin(kind, name, key, error).cls
        options = self._plugin_options(cls, name, own or {}, key, error or self.config.error)
        try:
            return cls(options, *args)
        except OptionError as exc:
            raise self.option_error(name, exc, key, error) from None

    def _entry_cipher(self, name: str, key: str, error: ErrorMaker,
                      on_bus: bool = False) -> tuple[type[Cipher], Cipher | None]:
        """An entry's cipher class, and an instance keyed from the file (None in a session,
        where the session keys it: its key options are not needed). A bus has no peer to
        handshake with: its entries keep the file's keys."""
        cls: type[Cipher] = self.plugin("cipher", name, key, error).cls
        session = self.config.secure and not on_bus
        if not session or not cls.session_key_size:
            if session and cls.authenticates:
                raise error(key, f"cipher {name!r} cannot be keyed from a session",
                            "pick a cipher that can (aead, nacl, fernet)")
            if name not in self.ciphers:  # static (or keyless: none)
                self.ciphers[name] = self._made("cipher", name, key, error, self.config.base_dir)
            return cls, self.ciphers[name]
        return cls, None

    def _options(self, plugin: str) -> Any:
        return self.config.plugins.get(plugin) or {}

    def option_error(self, plugin: str, exc: OptionError, asked_by: str,
                     error: ErrorMaker | None = None) -> ConfigError:
        """Locate a plugin's complaint at its option, or, when the file has no options for the
        plugin at all, at the key that asked for the plugin."""
        if f"plugins.{plugin}" not in self.config.lines:
            return (error or self.config.error)(asked_by, f"{plugin}: {exc.message}", exc.fix)
        key = f"plugins.{plugin}" + (f".{exc.key}" if exc.key else "")
        return self.config.error(key, exc.message, exc.fix)


def _kind(entry: TopicConfig | ServiceConfig) -> str:
    return "topic" if isinstance(entry, TopicConfig) else "service"


def _microcontroller(codec_cls: type[Codec], options: Any,
                     entry: TopicConfig | ServiceConfig) -> Any:
    """A MessagePack codec on a microcontroller entry writes as the entry's ``args`` and
    ``floats`` say, where its options declare them (the msgpack codec's do)."""
    if not (entry.framing.bare and codec_cls.messagepack and dataclasses.is_dataclass(options)
            and not isinstance(options, type)):
        return options
    declared = {f.name for f in dataclasses.fields(options)}
    wanted = {"args": entry.args, "floats": entry.floats}
    return dataclasses.replace(options, **{k: v for k, v in wanted.items() if k in declared})
