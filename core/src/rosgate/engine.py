"""The engine: turns a bringup.yaml into routes over links, and keeps them running.

``Engine(config).prepare()`` resolves everything that can be wrong in a file (plugins, options,
keys, message types, addresses) and raises :class:`ConfigError` naming the file, line and key.
``start()`` opens the ROS node and the links; ``stop()`` closes them.

Roles:

* **peer** — both files complete, no main line. A topic's id on the wire is a hash of its link
  name (``remote``), so both sides agree without talking. Receiving topics bind
  ``listen:port``; transmitting topics send (or connect) to ``peer:port``.
* **client** — connects its main line to ``server``, sends its topic list, and gets the topic ids
  back. Stream topics without a port ride the main line; datagram topics without a port use the
  server's main port number on that transport. The client starts every connection, so it can
  sit behind NAT; it says hello on each datagram link so the server learns where it is.
* **server** — accepts many clients; each client's topics become a :class:`Session` of routes,
  removed when the client goes.
"""

from __future__ import annotations

import json
import logging
import os
import random
import threading
import time
import zlib
from dataclasses import dataclass, field
from typing import Any, Callable

from . import envelope
from .cipher import Cipher
from .codec import Codec
from .config import BridgeConfig, TopicConfig, topic_from_mapping, topic_to_mapping
from .errors import ConfigError, LinkError, OptionError
from .links import Acceptor, DatagramLink, Link, StreamLink
from .plugins import Plugins
from .ros import RosNode, TypeNotFound, qos_profile, resolve_type
from .routes import ReceiveRoute, Route, TransmitRoute, Warner
from .transport import Address, StreamConnection, Transport

log = logging.getLogger("rosgate")

PROTOCOL = 1           # main-line control protocol version
HANDSHAKE_TIMEOUT = 10.0
CONNECT_TIMEOUT = 5.0
BACKOFF_MAX = 10.0
STATS_EVERY = float(os.environ.get("ROSGATE_STATS_EVERY", "60"))


def wire_id(name: str) -> int:
    """Peer role: a topic's id is derived from its link name, so both sides agree."""
    return zlib.crc32(name.encode()) or 1  # 0 is the control channel


@dataclass
class Prepared:
    """A topic with every plugin and type resolved."""

    config: TopicConfig
    msg_type: type
    codec_cls: type[Codec]
    transport: Transport
    cipher: Cipher
    index: int  # position in the file (or in the client's list), for error messages


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
        self.receivers: dict[int, ReceiveRoute] = {}
        self.link_drops: dict[str, int] = {}
        self.ros: RosNode | None = None
        self.stopping = threading.Event()
        self._closables: list[Any] = []
        self._lock = threading.RLock()
        self._role: Any = None

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
        return self

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
            codec_cls(msg_type, self.config.plugins.get(topic.codec) or {})
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
        return Prepared(topic, msg_type, codec_cls, transport, cipher, index)

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
                    other = seen.setdefault(wire_id(name), p)
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
                self.transports[name] = cls(self.config.plugins.get(name) or {})
            except OptionError as exc:
                raise self._option_error(name, exc, key) from None
        return self.transports[name]

    def cipher(self, name: str, key: str, error: Callable[..., ConfigError] | None = None) -> Cipher:
        if name not in self.ciphers:
            cls = self.plugin("cipher", name, key, error).cls
            try:
                self.ciphers[name] = cls(self.config.plugins.get(name) or {}, self.config.base_dir)
            except OptionError as exc:
                raise self._option_error(name, exc, key) from None
        return self.ciphers[name]

    def address(self, transport: Transport, text: str | None, key: str) -> Address:
        try:
            return transport.parse_address(text or "")
        except ValueError as exc:
            raise self.config.error(key, str(exc)) from None

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
        role = {"peer": PeerRole, "client": ClientRole, "server": ServerRole}[self.config.role]
        try:
            self._role = role(self)
            self._role.start()
        except LinkError as exc:
            self.stop()
            raise self.config.error(getattr(exc, "key", None) or "bridge", str(exc),
                                    "free the port, or pick another one") from None
        self._housekeeper = threading.Thread(target=self._housekeeping, name="housekeeping",
                                             daemon=True)
        self._housekeeper.start()
        log.info("%s: running as %s with %d topic(s)", self.config.name, self.config.role,
                 len(self.topics))
        return self

    def stop(self) -> None:
        if self.stopping.is_set():
            return
        self.stopping.set()
        if self.ros is not None:
            self.log_stats()  # before the routes and their counters go
        if self._role is not None:
            self._role.stop()
        for item in reversed(self._closables):
            item.close()
        self._closables.clear()
        if self.ros is not None:
            self.ros.close()

    def __enter__(self) -> "Engine":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def closing(self, item: Any) -> Any:
        """Close ``item`` when the engine stops."""
        self._closables.append(item)
        return item

    # -- building routes ---------------------------------------------------------------------
    def make_route(self, p: Prepared, topic_id: int, label: str, link: Link,
                   destination: Callable[[], Address | None] = lambda: None) -> Route:
        """Create a route and its ROS entity; a receive route is registered for dispatch."""
        t = p.config
        codec = p.codec_cls(p.msg_type, self.config.plugins.get(t.codec) or {})
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

    def remove_route(self, route: Route) -> None:
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

    def log_stats(self) -> None:
        for route in self.routes():
            c = route.counters
            drops = ", ".join(f"{k}={v}" for k, v in sorted(c.drops.items())) or "none"
            log.info("%s: sent %d (%d B), received %d (%d B), drops: %s", route.label, c.sent,
                     c.bytes_sent, c.received, c.bytes_received, drops)
        if self.link_drops:
            log.info("frames for no topic: %s", self.link_drops)


# -- roles -------------------------------------------------------------------------------------
class Role:
    """What the three roles share: datagram links by local address, and route bookkeeping."""

    def __init__(self, engine: Engine):
        self.engine = engine
        self.cfg = engine.config
        self.datagram_links: dict[tuple[str, Address], DatagramLink] = {}
        self.bare_routes: dict[DatagramLink, dict[str | None, ReceiveRoute]] = {}
        self._routes: list[Route] = []
        self._lock = threading.RLock()

    def start(self) -> None: ...

    def stop(self) -> None:
        for route in self._routes:
            self.engine.remove_route(route)
        self._routes.clear()

    def routes(self) -> list[Route]:
        with self._lock:
            return list(self._routes)

    def bare_receivers(self) -> list[ReceiveRoute]:
        with self._lock:
            return [r for routes in self.bare_routes.values() for r in routes.values()]

    def transmitter(self, topic_id: int) -> Route | None:
        with self._lock:
            return next((r for r in self._routes
                         if r.topic_id == topic_id and isinstance(r, TransmitRoute)), None)

    def add(self, route: Route) -> Route:
        with self._lock:
            self._routes.append(route)
        return route

    def datagram_link(self, transport: Transport, local: Address, bare: bool = False,
                      key: str | None = None) -> DatagramLink:
        """The link bound at ``local`` (shared by every topic on that port)."""
        with self._lock:
            found = self.datagram_links.get((transport.name, local))
            if found is not None:
                return found
            try:
                endpoint = transport.bind(local)
            except LinkError as exc:
                exc.key = key  # type: ignore[attr-defined]
                raise
            name = f"{transport.name}:{local[1]}" if local[1] else f"{transport.name}"
            if bare:
                link = DatagramLink(transport, endpoint, name,
                                    lambda d, l, s: self.engine.on_bare(self.bare_routes[l], d, l, s),
                                    self.engine.on_drop, bare=True)
                self.bare_routes[link] = {}
            else:
                link = DatagramLink(transport, endpoint, name, self.engine.on_frame,
                                    self.engine.on_drop)
            self.datagram_links[(transport.name, local)] = self.engine.closing(link)
            return link


class PeerRole(Role):
    """Both sides configured; no main line."""

    def start(self) -> None:
        engine, cfg = self.engine, self.cfg
        listen = cfg.listen or "0.0.0.0"
        for p in engine.topics:
            t = p.config
            key = f"topics[{p.index}].port"
            label = t.topic
            assert t.port is not None
            if p.transport.stream:
                self._start_stream(p, listen, key)
                continue
            if t.direction == "receive":
                link = self.datagram_link(p.transport, (listen, t.port), t.framing == "none", key)
                route = engine.make_route(p, wire_id(t.remote), label, link)
                if t.framing == "none":
                    for name in {t.topic, t.remote}:
                        self.bare_routes[link][name] = route  # type: ignore[assignment]
                    if not p.codec_cls.names_bare_frames:
                        self.bare_routes[link] = {None: route}  # type: ignore[assignment]
                elif t.topic != t.remote:
                    engine.receivers[wire_id(t.topic)] = route  # type: ignore[assignment]
            else:
                link = self.datagram_link(p.transport, (listen, 0), False, key)
                to = (cfg.peer or "", t.port)
                route = engine.make_route(p, wire_id(t.remote), label, link, lambda to=to: to)
            self.add(route)

    def _start_stream(self, p: Prepared, listen: str, key: str) -> None:
        t = p.config
        assert t.port is not None
        if t.direction == "receive":
            route = self.engine.make_route(p, wire_id(t.remote), t.topic, _NoLink())
            if t.topic != t.remote:
                self.engine.receivers[wire_id(t.topic)] = route  # type: ignore[assignment]
            self.add(route)
            self._listen(p.transport, (listen, t.port), key)
        else:
            slot = LinkSlot(f"{t.transport}->{self.cfg.peer}:{t.port}")
            self.add(self.engine.make_route(p, wire_id(t.remote), t.topic, slot))
            Connector(self.engine, p.transport, (self.cfg.peer or "", t.port), slot,
                      self.engine.on_frame).start()

    def _listen(self, transport: Transport, local: Address, key: str) -> None:
        if (transport.name, local) in self.datagram_links:
            return
        try:
            listener = transport.listen(local)
        except LinkError as exc:
            exc.key = key  # type: ignore[attr-defined]
            raise
        engine = self.engine

        def accepted(connection: StreamConnection, peer: Address) -> None:
            engine.closing(StreamLink(connection, f"{transport.name}:{local[1]}<-{peer[0]}", peer,
                                      engine.on_frame, engine.on_drop))

        engine.closing(Acceptor(listener, f"{transport.name}:{local[1]}", accepted))
        self.datagram_links[(transport.name, local)] = None  # type: ignore[assignment]


class LinkSlot(Link):
    """A stand-in for a stream link that comes and goes (connects, reconnects)."""

    def __init__(self, name: str):
        self.name = name
        self.current: StreamLink | None = None
        self.closed = threading.Event()

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        link = self.current
        if link is None or link.closed.is_set():
            return False
        return link.send(frame, topic_id, to)

    def close(self) -> None:
        self.closed.set()
        if self.current is not None:
            self.current.close()


class _NoLink(Link):
    """A receive route's link: frames come in through the engine, nothing goes out."""

    name = "in"
    closed = threading.Event()

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        return False

    def close(self) -> None:
        pass


class Connector:
    """Keeps a stream connection up: connect, and after a loss reconnect with capped backoff."""

    def __init__(self, engine: Engine, transport: Transport, address: Address, slot: LinkSlot,
                 on_frame: Callable[[bytes, Link, Address], None],
                 on_connected: Callable[[StreamLink], bool] | None = None):
        self.engine = engine
        self.transport = transport
        self.address = address
        self.slot = slot
        self.on_frame = on_frame
        self.on_connected = on_connected
        self.connected = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"connect-{slot.name}", daemon=True)
        engine.closing(self)

    def start(self) -> None:
        self._thread.start()

    def _loop(self) -> None:
        delay = 0.1
        stopping = self.engine.stopping
        while not stopping.is_set() and not self.slot.closed.is_set():
            try:
                connection = self.transport.connect(self.address, CONNECT_TIMEOUT)
            except OSError as exc:
                log.debug("%s: connect failed: %s", self.slot.name, exc)
                stopping.wait(delay * random.uniform(0.5, 1.0))
                delay = min(delay * 2, BACKOFF_MAX)
                continue
            link = StreamLink(connection, self.slot.name, self.address, self.on_frame,
                              self.engine.on_drop)
            if self.on_connected is not None and not self.on_connected(link):
                link.close()
                stopping.wait(delay)
                delay = min(delay * 2, BACKOFF_MAX)
                continue
            self.slot.current = link
            self.connected.set()
            delay = 0.1
            while not link.closed.wait(0.5):
                if stopping.is_set() or self.slot.closed.is_set():
                    break
            self.connected.clear()
            link.close()

    def close(self) -> None:
        self.slot.close()
        self._thread.join(timeout=3) if self._thread.is_alive() else None


# -- client / server ---------------------------------------------------------------------------
def control(message: dict[str, Any]) -> bytes:
    """A control frame for the main line: an envelope on topic 0 and a JSON body.

    JSON, not pickle: a peer's bytes never become code."""
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
    from dataclasses import replace

    return replace(t, topic=t.remote, remote=t.topic,
                   direction="receive" if t.direction == "transmit" else "transmit")


class ClientRole(Role):
    def __init__(self, engine: Engine):
        super().__init__(engine)
        self.main = LinkSlot(f"main->{self.cfg.server}")
        self.session: int | None = None
        self.token = b""
        self.server_name: str | None = None
        self.connected = threading.Event()
        self.hello_to: set[tuple[DatagramLink, Address]] = set()  # every server port we use
        self._welcome: dict[str, Any] | None = None
        self._answer = threading.Event()
        main = engine.transports[self.cfg.main_line]
        self.connector = Connector(engine, main, engine.main_address, self.main, self._on_main_frame,
                                   self._handshake)

    def start(self) -> None:
        self.connector.start()
        self._pinger = threading.Thread(target=self._ping_loop, name="client-ping", daemon=True)
        self._pinger.start()

    def stop(self) -> None:
        self.connector.close()
        super().stop()

    def _on_main_frame(self, frame: bytes, link: Link, source: Address) -> None:
        if frame[3:4] and frame[3] & envelope.FLAG_CONTROL and frame[:2] == envelope.MAGIC:
            message = parse_control(frame)
            if message is None:
                self.engine.link_drop(link, "bad_control", "unreadable control message")
            elif message["type"] in ("welcome", "refused"):
                self._welcome = message
                self._answer.set()
            return
        self.engine.on_frame(frame, link, source)

    def _handshake(self, link: StreamLink) -> bool:
        """Send our topics; build the routes from the server's answer."""
        self._teardown()
        self._answer.clear()
        self._welcome = None
        self.main.current = link
        link.send(control({"type": "hello", "protocol": PROTOCOL, "name": self.cfg.name,
                           "topics": [topic_to_mapping(p.config) for p in self.engine.topics]}), 0)
        if not self._answer.wait(HANDSHAKE_TIMEOUT) or self._welcome is None:
            log.warning("%s: no answer to the handshake from %s", self.cfg.name, self.cfg.server)
            return False
        answer = self._welcome
        if answer["type"] == "refused":
            log.error("%s: the server refused our topics: %s", self.cfg.name, answer.get("error"))
            return False
        try:
            self._build(answer)
        except (KeyError, TypeError, ValueError, LinkError) as exc:
            log.error("%s: cannot use the server's answer: %s", self.cfg.name, exc)
            self._teardown()
            return False
        log.info("%s: connected to server %r at %s", self.cfg.name, self.server_name, self.cfg.server)
        self.connected.set()
        threading.Thread(target=self._watch, args=(link,), daemon=True).start()
        return True

    def _build(self, answer: dict[str, Any]) -> None:
        engine = self.engine
        ids = [int(i) for i in answer["topic_ids"]]
        if len(ids) != len(engine.topics):
            raise ValueError("topic id count does not match")
        self.session = int(answer["session"])
        self.token = bytes.fromhex(answer["token"])
        self.server_name = str(answer["name"])
        host, main_port = engine.main_address
        for p, topic_id in zip(engine.topics, ids):
            t = p.config
            label = f"{t.topic} ({'to' if t.direction == 'transmit' else 'from'} {self.server_name})"
            if p.transport.stream:
                if t.port is None:
                    link: Link = self.main
                else:
                    link = self._dedicated_stream(p, (host, t.port))
                self.add(engine.make_route(p, topic_id, label, link))
            else:
                to = (host, t.port or main_port)
                link = self.datagram_link(p.transport, ("::" if ":" in host else "0.0.0.0", 0))
                self.add(engine.make_route(p, topic_id, label, link, lambda to=to: to))
                self.hello_to.add((link, to))
        self._say_hello()

    def _dedicated_stream(self, p: Prepared, address: Address) -> LinkSlot:
        slot = LinkSlot(f"{p.config.transport}->{address[0]}:{address[1]}")

        def introduce(link: StreamLink) -> bool:
            assert self.session is not None
            return link.send(hello_datagram(self.session, self.token), 0)

        connector = Connector(self.engine, p.transport, address, slot, self.engine.on_frame,
                              introduce)
        connector.start()
        self._extra.append(connector)
        return slot

    def _say_hello(self) -> None:
        if self.session is None:
            return
        hello = hello_datagram(self.session, self.token)
        for link, to in list(self.hello_to):
            link.send(hello, 0, to)

    def _watch(self, link: StreamLink) -> None:
        link.closed.wait()
        if not self.engine.stopping.is_set():
            log.warning("%s: main line to %s lost; reconnecting", self.cfg.name, self.cfg.server)
        self.connected.clear()
        self._teardown()

    def _ping_loop(self) -> None:
        while not self.engine.stopping.wait(self.cfg.heartbeat):
            if self.connected.is_set():
                self.main.send(control({"type": "ping"}), 0)
                self._say_hello()

    def _teardown(self) -> None:
        for connector in getattr(self, "_extra", []):
            connector.close()
        self._extra: list[Connector] = []
        super().stop()
        with self._lock:
            links = list(self.datagram_links.values())
            self.datagram_links.clear()
            self.hello_to.clear()
        for link in links:
            link.close()


@dataclass
class Session:
    """One connected client, as the server sees it."""

    id: int
    token: bytes
    name: str
    main: StreamLink
    routes: list[Route] = field(default_factory=list)
    addresses: dict[DatagramLink, Address] = field(default_factory=dict)
    streams: dict[int, StreamLink] = field(default_factory=dict)  # port -> dedicated connection


class ServerRole(Role):
    def __init__(self, engine: Engine):
        super().__init__(engine)
        self.sessions: dict[int, Session] = {}
        self._ids = iter(range(1, 2**32))
        self._listening: set[tuple[str, int]] = set()

    def start(self) -> None:
        main = self.engine.transports[self.cfg.main_line]
        try:
            listener = main.listen(self.engine.main_address)
        except LinkError as exc:
            exc.key = "bridge.server"  # type: ignore[attr-defined]
            raise
        self.engine.closing(Acceptor(listener, f"main:{self.engine.main_address[1]}",
                                     self._accepted))
        threading.Thread(target=self._ping_loop, name="server-ping", daemon=True).start()

    def stop(self) -> None:
        for session in list(self.sessions.values()):
            self._end(session)
        super().stop()

    def routes(self) -> list[Route]:
        with self._lock:
            return [r for s in self.sessions.values() for r in s.routes]

    def transmitter(self, topic_id: int) -> Route | None:
        return next((r for r in self.routes()
                     if r.topic_id == topic_id and isinstance(r, TransmitRoute)), None)

    def _accepted(self, connection: StreamConnection, peer: Address) -> None:
        holder: dict[str, Session] = {}

        def on_frame(frame: bytes, link: Link, source: Address) -> None:
            session = holder.get("session")
            if frame[:2] == envelope.MAGIC and len(frame) > 3 and frame[3] & envelope.FLAG_CONTROL:
                message = parse_control(frame)
                if message is None:
                    self.engine.link_drop(link, "bad_control", f"from {source}")
                elif message["type"] == "hello" and session is None:
                    session = self._welcome(message, link, peer)  # type: ignore[arg-type]
                    if session is not None:
                        holder["session"] = session
                return
            if session is None:
                self.engine.link_drop(link, "before_handshake", f"data from {source}")
                return
            self.engine.on_frame(frame, link, source)

        def on_close(link: StreamLink) -> None:
            session = holder.get("session")
            if session is not None and session.main is link:
                log.info("client %r left", session.name)
                self._end(session)

        self.engine.closing(StreamLink(connection, f"main<-{peer[0]}:{peer[1]}", peer, on_frame,
                                       self.engine.on_drop, on_close))

    def _welcome(self, hello: dict[str, Any], link: StreamLink, peer: Address) -> Session | None:
        name = str(hello.get("name", "?"))
        try:
            if hello.get("protocol") != PROTOCOL:
                raise ConfigError(f"protocol {hello.get('protocol')!r} is not {PROTOCOL}",
                                  file=f"client {name}", fix="run the same rosgate version on both")
            session = Session(next(self._ids), os.urandom(16), name, link)
            prepared = self._prepare_client_topics(hello, name)
            with self._lock:
                self.sessions[session.id] = session
            for p in prepared:
                session.routes.append(self._route(session, p))
        except ConfigError as exc:
            log.error("refused client %r from %s: %s", name, peer[0], exc)
            link.send(control({"type": "refused", "error": str(exc)}), 0)
            if "session" in locals() and session.id in self.sessions:
                self._end(session)
            return None
        except LinkError as exc:
            log.error("refused client %r: %s", name, exc)
            link.send(control({"type": "refused", "error": str(exc)}), 0)
            self._end(session)
            return None
        link.send(control({"type": "welcome", "name": self.cfg.name, "session": session.id,
                           "token": session.token.hex(),
                           "topic_ids": [r.topic_id for r in session.routes]}), 0)
        log.info("client %r connected from %s with %d topic(s)", name, peer[0], len(session.routes))
        return session

    def _prepare_client_topics(self, hello: dict[str, Any], name: str) -> list[Prepared]:
        topics = hello.get("topics")
        if not isinstance(topics, list):
            raise ConfigError("hello without a topic list", file=f"client {name}")
        where = f"client {name}"

        def error(key: str, message: str, fix: str | None = None) -> ConfigError:
            return ConfigError(message, file=where, key=key, fix=fix)

        prepared = []
        for i, mapping in enumerate(topics):
            if not isinstance(mapping, dict):
                raise error(f"topics[{i}]", "not a mapping")
            t = topic_from_mapping(mapping, self.cfg.defaults, where, index=i)
            prepared.append(self.engine.prepare_topic(flipped(t), i, "topics", error))
        return prepared

    def _route(self, session: Session, p: Prepared) -> Route:
        engine = self.engine
        t = p.config
        topic_id = next(self._ids)
        label = f"{t.topic} ({'to' if t.direction == 'transmit' else 'from'} {session.name})"
        host, main_port = engine.main_address
        if p.transport.stream:
            if t.port is None:
                link: Link = session.main
            else:
                self._listen(p.transport, (host, t.port))
                link = _SessionStream(session, t.port)
            return engine.make_route(p, topic_id, label, link)
        link = self.datagram_link(p.transport, (host, t.port or main_port))
        return engine.make_route(p, topic_id, label, link,
                                 lambda link=link: session.addresses.get(link))  # type: ignore[misc]

    def _listen(self, transport: Transport, local: Address) -> None:
        with self._lock:
            if (transport.name, local[1]) in self._listening:
                return
            listener = transport.listen(local)
            self._listening.add((transport.name, local[1]))

        port = local[1]

        def on_frame(frame: bytes, link: Link, source: Address) -> None:
            # the first frame on a dedicated connection says whose it is
            try:
                header = envelope.unpack(frame)
            except envelope.EnvelopeError:
                header = None
            if header is not None and header.flags & envelope.FLAG_HELLO:
                session = self.sessions.get(header.topic_id)
                if session is not None and frame[envelope.SIZE:] == session.token:
                    session.streams[port] = link  # type: ignore[assignment]
                else:
                    self.engine.link_drop(link, "bad_hello", f"from {source}")
                return
            self.engine.on_frame(frame, link, source)

        def accepted(connection: StreamConnection, peer: Address) -> None:
            self.engine.closing(StreamLink(connection, f"{transport.name}:{port}<-{peer[0]}",
                                           peer, on_frame, self.engine.on_drop))

        self.engine.closing(Acceptor(listener, f"{transport.name}:{local[1]}", accepted))

    def on_hello(self, header: envelope.Header, frame: bytes, link: Link, source: Address) -> None:
        session = self.sessions.get(header.topic_id)
        if session is None or frame[envelope.SIZE:] != session.token:
            self.engine.link_drop(link, "bad_hello", f"from {source}")
            return
        if isinstance(link, DatagramLink) and session.addresses.get(link) != source:
            session.addresses[link] = source
            log.debug("client %r is at %s on %s", session.name, source, link.name)

    def _end(self, session: Session) -> None:
        with self._lock:
            if self.sessions.pop(session.id, None) is None:
                return
        for route in session.routes:
            self.engine.remove_route(route)
        for stream in session.streams.values():
            stream.close()
        session.main.close()

    def _ping_loop(self) -> None:
        while not self.engine.stopping.wait(self.cfg.heartbeat):
            for session in list(self.sessions.values()):
                session.main.send(control({"type": "ping"}), 0)


class _SessionStream(Link):
    """A server route on a dedicated stream port: the client's connection there, once it came."""

    def __init__(self, session: Session, port: int):
        self.session = session
        self.port = port
        self.name = f"port {port} of {session.name}"
        self.closed = threading.Event()

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        link = self.session.streams.get(self.port)
        return link.send(frame, topic_id) if link is not None else False

    def close(self) -> None:
        pass
