"""The engine: turns a bringup.yaml into routes over links, and keeps them running.

``Engine(config).prepare()`` resolves everything that can be wrong in a file (plugins, options,
keys, message types, addresses) and raises :class:`ConfigError` naming the file, line and key.
``start()`` opens the ROS node and the links; ``stop()`` closes them.

The engine owns what every role shares: plugins, ciphers, the ROS node, the table of receiving
routes that every frame is dispatched through, and housekeeping (stale topics, statistics).
The role (roles.py: peer; client.py; server.py) decides which links exist and which routes go
over them.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from . import envelope
from .cipher import Cipher
from .codec import Codec
from .config import BridgeConfig, ServiceConfig, TopicConfig
from .envelope import topic_id_for
from .errors import ConfigError, LinkError, OptionError
from .links import Link, LinkSlot, QueueLimits
from .options import parse
from .plugins import Plugins
from .ros import RosNode, TypeNotFound, is_reliable, qos_profile, resolve_type
from .routes import ReceiveRoute, Route, TransmitRoute, Warner
from .services import ServiceCodec, ServiceRoute, ServiceTable
from .transport import Address, Transport

log = logging.getLogger("rosgate")

STATS_EVERY = float(os.environ.get("ROSGATE_STATS_EVERY", "60"))


@dataclass
class Prepared:
    """A topic with every plugin and type resolved."""

    config: TopicConfig
    msg_type: type
    codec_cls: type[Codec]
    transport: Transport
    cipher: Cipher
    index: int  # position in the file (or in the client's list), for error messages
    address: Address  # the far side; a peer's receiving topic: where to listen
    reliable: bool  # frames wait out a stream link's loss (reliable QoS)

    @property
    def name(self) -> str:
        return self.config.topic


@dataclass
class PreparedService:
    """A service with every plugin and type resolved."""

    config: ServiceConfig
    srv_type: type
    codec_cls: type[Codec]
    transport: Transport
    cipher: Cipher
    index: int
    address: Address  # as for a topic: the far side, or where a peer listens
    # calls are not held while a link is down: the caller's timeout answers them instead
    reliable: bool = False

    @property
    def name(self) -> str:
        return self.config.service

    def codec(self, options: dict[str, dict]) -> ServiceCodec:
        return ServiceCodec(self.codec_cls, self.srv_type,
                            parse(self.codec_cls, options.get(self.config.codec) or {}))


class Engine:
    def __init__(self, config: BridgeConfig, plugins: Plugins | None = None,
                 domain_id: int | None = None):
        self.config = config
        self.plugins = plugins or Plugins.discover()
        self.domain_id = domain_id
        self.warner = Warner()
        self.transports: dict[str, Transport] = {}
        self.ciphers: dict[str, Cipher] = {}
        self.topics: list[Prepared] = []
        self.services: list[PreparedService] = []
        self.receivers: dict[int, ReceiveRoute] = {}
        self.link_drops: dict[str, int] = {}
        self.ros: RosNode | None = None
        self.stopping = threading.Event()
        self.queue_limits = QueueLimits(config.queue_frames, config.queue_bytes)
        self._closables: dict[int, Any] = {}  # id -> object, in opening order
        self._lock = threading.RLock()
        self._role: Any = None
        self.service_table: ServiceTable | None = None  # made with the ROS node, in start()

    # -- preparation: every error a file can contain, before anything opens ----------------
    def prepare(self) -> "Engine":
        cfg = self.config
        if cfg.role != "peer":
            main = self.transport(cfg.main_line, "bridge.main_line")
            if not main.stream:
                raise cfg.error("bridge.main_line", f"{cfg.main_line!r} is not a stream transport",
                                "the main line needs a stream link such as tcp or bt")
            self.main_address = self.address(main, cfg.server, "bridge.server")
        for key in ("transport", "codec", "cipher"):
            self.plugin(key, cfg.defaults[key], f"bridge.defaults.{key}")
        self.topics = [self.prepare_topic(t, i, "topics") for i, t in enumerate(cfg.topics)]
        self._check_shared_ports(self.topics)
        self.services = [self.prepare_service(s, i, "services") for i, s in enumerate(cfg.services)]
        return self

    def prepare_service(self, service: ServiceConfig, index: int, section: str,
                        error: Callable[..., ConfigError] | None = None) -> PreparedService:
        error = error or self.config.error
        key = f"{section}[{index}]"
        transport = self.transport(service.transport, f"{key}.transport", error)
        codec_cls = self.plugin("codec", service.codec, f"{key}.codec", error).cls
        cipher = self.cipher(service.cipher, f"{key}.cipher", error)
        try:
            srv_type = resolve_type(service.type)
        except TypeNotFound as exc:
            raise error(f"{key}.type", str(exc)) from None
        prepared = PreparedService(service, srv_type, codec_cls, transport, cipher, index,
                                   self.topic_address(transport, service, key, error))
        try:
            prepared.codec(self.config.plugins)
        except OptionError as exc:
            raise self._option_error(service.codec, exc, f"{key}.codec") from None
        if service.framing == "serial_datagram":
            if self.config.role != "peer":
                raise error(f"{key}.framing", "framing serial_datagram is for microcontroller "
                            "peers, which have no main line", "use role: peer for this bridge")
            if not transport.stream:
                raise error(f"{key}.transport", "framing serial_datagram needs a stream transport "
                            "(one connection per call)", "use transport: tcp")
            if not codec_cls.names_bare_frames:
                raise error(f"{key}.codec", f"codec {service.codec} does not put the service's "
                            "name on the wire", "use codec: msgpack")
        if (self.config.role == "client" and transport.stream and service.port is None
                and service.transport != self.config.main_line):
            raise error(f"{key}.port", f"a service on {service.transport} needs a port of its own "
                        f"(only {self.config.main_line} services ride the main line)",
                        "add port: <number>")
        return prepared

    def prepare_topic(self, topic: TopicConfig, index: int, section: str,
                      error: Callable[..., ConfigError] | None = None) -> Prepared:
        error = error or self.config.error
        key = f"{section}[{index}]"
        transport = self.transport(topic.transport, f"{key}.transport", error)
        codec_cls = self.plugin("codec", topic.codec, f"{key}.codec", error).cls
        cipher = self.cipher(topic.cipher, f"{key}.cipher", error)
        try:
            msg_type = resolve_type(topic.type)
        except TypeNotFound as exc:
            raise error(f"{key}.type", str(exc)) from None
        try:
            codec_cls(msg_type, parse(codec_cls, self.config.plugins.get(topic.codec) or {}))
        except OptionError as exc:
            raise self._option_error(topic.codec, exc, f"{key}.codec") from None
        if topic.framing == "none" and transport.stream:
            raise error(f"{key}.framing", "framing: none needs a datagram transport (udp, can, ...)",
                        "use framing: rosgate on stream links")
        if (self.config.role == "client" and transport.stream and topic.port is None
                and topic.transport != self.config.main_line):
            raise error(f"{key}.port", f"a topic on {topic.transport} needs a port of its own "
                        f"(only {self.config.main_line} topics ride the main line)",
                        "add port: <number>")
        address = self.topic_address(transport, topic, key, error)
        return Prepared(topic, msg_type, codec_cls, transport, cipher, index, address,
                        is_reliable(topic.qos))

    def topic_address(self, transport: Transport, topic: TopicConfig | ServiceConfig, key: str,
                      error: Callable[..., ConfigError]) -> Address:
        """The address a topic's link uses, from the bridge's hosts and the topic's port, as its
        transport accepts it (an RFCOMM channel is not any port)."""
        cfg = self.config
        if cfg.role == "peer":
            host = cfg.listen if topic.direction == "receive" else cfg.peer
            where = "bridge.listen" if topic.direction == "receive" else "bridge.peer"
        else:
            host = self.main_address[0]
            where = "bridge.server"
        port = topic.port or self.main_address[1]
        try:
            return transport.check_address((host or "", port))
        except ValueError as exc:
            raise error(f"{key}.port" if topic.port else where, str(exc),
                        f"this topic's {topic.transport} address is {where} with port {port}") \
                from None

    def _check_shared_ports(self, topics: list[Prepared]) -> None:
        """Topics that share a receiving port must be told apart on it."""
        by_port: dict[tuple[str, int | None], list[Prepared]] = {}
        for p in topics:
            if p.config.direction == "receive":
                by_port.setdefault((p.config.transport, p.config.port), []).append(p)
        for group in by_port.values():
            bare = [p for p in group if p.config.framing == "none"]
            if bare and len(bare) != len(group):
                p = bare[0]
                raise self.config.error(f"topics[{p.index}].framing",
                                        "topics on one port must all use the same framing")
            if len(bare) > 1 and not all(p.codec_cls.names_bare_frames for p in bare):
                p = next(p for p in bare if not p.codec_cls.names_bare_frames)
                raise self.config.error(
                    f"topics[{p.index}].port", f"codec {p.config.codec} does not name its frames, "
                    "so with framing: none this topic needs a port of its own",
                    "give each such topic its own port, or use codec msgpack")
        if self.config.role == "peer":
            seen: dict[int, Prepared] = {}
            for p in topics:
                for name in {p.config.topic, p.config.remote} if p.config.direction == "receive" \
                        else {p.config.remote}:
                    other = seen.setdefault(topic_id_for(name), p)
                    if other is not p and other.config.direction == p.config.direction:
                        raise self.config.error(
                            f"topics[{p.index}].remote",
                            f"link name {name!r} collides with topics[{other.index}]",
                            "rename one of them (remote: ...)")

    def plugin(self, kind: str, name: str, key: str,
               error: Callable[..., ConfigError] | None = None) -> Any:
        registration = self.plugins.get(kind, name)
        if registration is None:
            message, fix = self.plugins.explain_missing(kind, name)
            raise (error or self.config.error)(key, message, fix)
        return registration

    def transport(self, name: str, key: str,
                  error: Callable[..., ConfigError] | None = None) -> Transport:
        if name not in self.transports:
            cls = self.plugin("transport", name, key, error).cls
            try:
                self.transports[name] = cls(parse(cls, self.config.plugins.get(name) or {}))
            except OptionError as exc:
                raise self._option_error(name, exc, key) from None
        return self.transports[name]

    def cipher(self, name: str, key: str, error: Callable[..., ConfigError] | None = None) -> Cipher:
        if name not in self.ciphers:
            cls = self.plugin("cipher", name, key, error).cls
            try:
                self.ciphers[name] = cls(parse(cls, self.config.plugins.get(name) or {}),
                                         self.config.base_dir)
            except OptionError as exc:
                raise self._option_error(name, exc, key) from None
        return self.ciphers[name]

    def address(self, transport: Transport, text: str | None, key: str) -> Address:
        try:
            return transport.check_address(transport.parse_address(text or ""))
        except ValueError as exc:
            raise self.config.error(key, str(exc)) from None

    def slot(self, name: str) -> LinkSlot:
        """A place for a stream link that reconnects; reliable frames wait in it while it is down."""
        return LinkSlot(name, self.on_drop, self.queue_limits)

    def _option_error(self, plugin: str, exc: OptionError, asked_by: str) -> ConfigError:
        """Locate a plugin's complaint at its option, or, when the file has no options for the
        plugin at all, at the key that asked for the plugin."""
        if f"plugins.{plugin}" not in self.config.lines:
            return self.config.error(asked_by, f"{plugin}: {exc.message}", exc.fix)
        key = f"plugins.{plugin}" + (f".{exc.key}" if exc.key else "")
        return self.config.error(key, exc.message, exc.fix)

    # -- running -----------------------------------------------------------------------------
    def start(self) -> "Engine":
        if not self.topics and self.config.topics:
            self.prepare()
        self.ros = RosNode(self.config.name, self.domain_id)
        self.service_table = self.closing(ServiceTable(self))
        from .client import ClientRole
        from .roles import PeerRole
        from .server import ServerRole

        role = {"peer": PeerRole, "client": ClientRole, "server": ServerRole}[self.config.role]
        try:
            self._role = role(self)
            self._role.start()
        except ConfigError:
            self.stop()
            raise
        self._housekeeper = threading.Thread(target=self._housekeeping, name="housekeeping",
                                             daemon=True)
        self._housekeeper.start()
        log.info("%s: running as %s with %d topic(s) and %d service(s)", self.config.name,
                 self.config.role, len(self.topics), len(self.services))
        return self

    def stop(self) -> None:
        if self.stopping.is_set():
            return
        self.stopping.set()
        if self.ros is not None:
            self.log_stats()  # before the routes and their counters go
        if self._role is not None:
            self._role.stop()
        for item in reversed(list(self._closables.values())):
            item.close()
        self._closables.clear()
        if self.ros is not None:
            self.ros.close()

    def __enter__(self) -> "Engine":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def closing(self, item: Any) -> Any:
        """Close ``item`` when the engine stops (unless it was :meth:`forget`-ten first)."""
        self._closables[id(item)] = item
        return item

    def forget(self, item: Any) -> None:
        """``item`` closed by itself (a connection that ended): nothing to close at stop."""
        self._closables.pop(id(item), None)

    def bind_error(self, exc: LinkError, key: str) -> ConfigError:
        """A link that cannot be opened, located at the key that named it."""
        return self.config.error(key, str(exc), exc.fix or "free the port, or pick another one")

    # -- building routes ---------------------------------------------------------------------
    def make_route(self, p: Prepared | PreparedService, topic_id: int, label: str, link: Link,
                   destination: Callable[[], Address | None] = lambda: None) -> Route:
        """Create a route and its ROS entity; a receive route is registered for dispatch."""
        if isinstance(p, PreparedService):
            assert self.service_table is not None
            return self.service_table.make_route(p, topic_id, label, link, destination)
        t = p.config
        codec = p.codec_cls(p.msg_type,
                            parse(p.codec_cls, self.config.plugins.get(t.codec) or {}))
        codec.authenticated = p.cipher.authenticates and t.framing != "none"
        qos = qos_profile(t.qos)
        bare = t.framing == "none"
        assert self.ros is not None
        if t.direction == "transmit":
            route: Route = TransmitRoute(t, topic_id, codec, p.cipher, self.warner, label,
                                         link=link, destination=destination, bare=bare)
            route.entity = self.ros.subscribe(p.msg_type, t.topic, qos, route.on_message, codec.raw)
        else:
            route = ReceiveRoute(t, topic_id, codec, p.cipher, self.warner, label)
            route.entity = self.ros.publisher(p.msg_type, t.topic, qos)
            if not bare:
                with self._lock:
                    self.receivers[topic_id] = route
        return route

    def renumber(self, route: Route, topic_id: int) -> None:
        """Give a route the id a restarted server chose for it."""
        with self._lock:
            if self.receivers.get(route.topic_id) is route:
                del self.receivers[route.topic_id]
            route.topic_id = topic_id
            if isinstance(route, ReceiveRoute) and route.topic.framing != "none":
                self.receivers[topic_id] = route

    def remove_route(self, route: Route) -> None:
        if isinstance(route, ServiceRoute) and self.service_table is not None:
            self.service_table.remove(route)
        with self._lock:
            if self.receivers.get(route.topic_id) is route:
                del self.receivers[route.topic_id]
        if self.ros is not None and route.entity is not None:
            self.ros.destroy(route.entity)
            route.entity = None

    # -- receiving: every frame from every link comes through here ---------------------------
    def on_frame(self, frame: bytes, link: Link, source: Address) -> None:
        try:
            header = envelope.unpack(frame)
        except envelope.EnvelopeError as exc:
            self.link_drop(link, f"{exc}_frame", f"{len(frame)} bytes from {source}")
            return
        if header.flags & envelope.FLAG_HELLO:
            self._role.on_hello(header, frame, link, source)
            return
        if header.flags & (envelope.FLAG_REQUEST | envelope.FLAG_REPLY):
            assert self.service_table is not None
            self.service_table.on_frame(header, frame, link, source)
            return
        route = self.receivers.get(header.topic_id)
        if route is None:
            self.link_drop(link, "unknown_topic", f"topic id {header.topic_id} from {source}")
            return
        route.on_frame(header, frame)

    def on_bare(self, routes: dict[str | None, ReceiveRoute], datagram: bytes, link: Link,
                source: Address) -> None:
        """``framing: none``: the codec of the port's topics finds the name in the datagram."""
        codec = next(iter(routes.values())).codec
        try:
            name, rest = codec.split_bare(datagram)
        except Exception as exc:
            self.link_drop(link, "unnamed_frame", f"{len(datagram)} bytes from {source}: {exc}")
            return
        route = routes.get(name) if name is not None else next(iter(routes.values()))
        if route is None:
            self.link_drop(link, "unknown_topic", f"name {name!r} from {source}")
            return
        route.on_bare(rest, len(datagram))

    def link_drop(self, link: Link | None, reason: str, detail: str) -> None:
        name = link.name if link is not None else "link"
        with self._lock:
            self.link_drops[reason] = self.link_drops.get(reason, 0) + 1
        self.warner.warn(name, reason, detail)

    def on_drop(self, topic_id: int | None, reason: str) -> None:
        """A link lost a frame (fragment lost, queue full, send error)."""
        route = self.receivers.get(topic_id) if topic_id is not None else None
        if route is None and topic_id is not None:
            route = self._role.transmitter(topic_id) if self._role else None
        if route is not None:
            route.drop(reason)
        else:
            self.link_drop(None, reason, "on a link")

    # -- housekeeping: stale topics and statistics ------------------------------------------
    def _housekeeping(self) -> None:
        cfg = self.config
        next_stats = time.monotonic() + STATS_EVERY
        while not self.stopping.wait(0.5):
            now = time.monotonic()
            for route in list(self.receivers.values()) + self._role.bare_receivers():
                silence = now - route.last_received
                due = cfg.stale_after * (route.stale_warnings_given + 1)
                if silence >= due and route.stale_warnings_given < cfg.stale_warnings:
                    route.stale_warnings_given += 1
                    log.warning("%s: no data for %.0f s (warning %d of %d)", route.label, silence,
                                route.stale_warnings_given, cfg.stale_warnings)
            if now >= next_stats:
                next_stats = now + STATS_EVERY
                self.log_stats()

    def routes(self) -> list[Route]:
        return self._role.routes() if self._role else []

    def stats(self) -> dict[str, Any]:
        """Counters per route, plus drops that belong to no topic."""
        return {"routes": {r.label: r.counters.snapshot() for r in self.routes()},
                "link_drops": dict(self.link_drops)}

    def log_stats(self, routes: list[Route] | None = None) -> None:
        """Log the counters of ``routes`` (default: every route, and the frames for no topic)."""
        for route in self.routes() if routes is None else routes:
            c = route.counters
            drops = ", ".join(f"{k}={v}" for k, v in sorted(c.drops.items())) or "none"
            lost = f", lost on the way {c.lost}" if c.lost else ""
            log.info("%s: sent %d (%d B), received %d (%d B)%s, drops: %s", route.label, c.sent,
                     c.bytes_sent, c.received, c.bytes_received, lost, drops)
        if routes is None and self.link_drops:
            log.info("frames for no topic: %s", self.link_drops)
