"""Roles: which links a bridge opens and which routes go over them — peer (both files
complete), client (a main line to a server, :mod:`.mainline`) and server (a session per client).
A role works with a :class:`Bridge`, never with the engine; :class:`Role` holds what they share.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..admission import Acceptor, ConnectionLimits, Sources, proven
from ..config import BridgeConfig, LinkConfig
from ..drops import Drop, Reason
from ..errors import ConfigError, LinkError
from ..links.base import FrameHandler, Link
from ..links.datagram import DatagramLink
from ..links.lifetime import Lifetime
from ..resolver.plan import Plan, Resolver
from ..router import Router
from ..routes import BarePort, Route
from ..secure import (
    HandshakeError,
    KeySchedule,
    SecureConnection,
    SessionKeys,
    initiate,
    respond,
)
from ..spec import CONTROL, ServiceSpec, TopicSpec
from ..streamlink.connector import Backoff
from ..streamlink.link import StreamLink, Untrusted
from ..streamlink.slot import LinkSlot, QueueLimits
from ..transport import (
    Address,
    DatagramTransport,
    StreamConnection,
    StreamTransport,
    Transport,
    line_budget,
)
from ..warn import Warner
from ..wire import envelope
from .mainline import control, key_label, parse_control

log = logging.getLogger("rosgate")

#: (connection, peer, then): authenticate an accepted connection, then hand it to ``then``
Handshake = Callable[[StreamConnection, Address, Callable[[StreamConnection], None]], None]


UNBIND_WAIT = 5.0  # seconds binding a datagram port waits for a session that ended to close it
REFUSAL_EVERY = 60.0  # seconds between two log lines about one refusal


@dataclass
class Bridge:
    """What a role works with."""

    config: BridgeConfig
    plan: Plan
    resolver: Resolver  # a server resolves the entries its clients send
    router: Router
    life: Lifetime

    def slot(self, name: str, resends: bool = False) -> LinkSlot:
        """A place for a stream link that reconnects; reliable frames wait in it while down
        (``resends``: and what it wrote is kept, to be written again: a main line)."""
        return LinkSlot(name, QueueLimits(self.config.queue_frames, self.config.queue_bytes),
                        resends)

    @property
    def backoff(self) -> Backoff:
        return Backoff(self.config.reconnect_min, self.config.reconnect_max)

    def budget(self, transport: Transport) -> LinkConfig | None:
        return line_budget(self.config.links, transport)

    def link_error(self, exc: LinkError, key: str) -> ConfigError:
        return self.config.error(key, str(exc), exc.fix or "free the port, or pick another one")


class Role:
    """What the roles share: datagram links and listening ports (within the connection limits),
    the sources links take frames from, and the lines of control messages."""

    def __init__(self, bridge: Bridge):
        self.bridge = bridge
        self.cfg = bridge.config
        self.router = bridge.router
        self.life = bridge.life
        self.datagram_links: dict[tuple[str, Address], DatagramLink] = {}
        self.bare_ports: dict[DatagramLink, BarePort] = {}
        self.listening: dict[tuple[str, Address], Acceptor] = {}
        #: who holds each datagram link and listener (a server's sessions): released together
        self._holders: dict[tuple[str, str, Address], set[int]] = {}
        self.control = Control(self.router)
        limits = self.cfg.limits
        self.limits = ConnectionLimits(limits.connections, limits.connections_per_source)
        #: what a connection a client opened may do before it is trusted
        self.untrusted = Untrusted(limits.max_frame_before_auth, limits.handshake_timeout)
        self.refusals = Refusals(REFUSAL_EVERY)
        self._lock = threading.RLock()
        #: datagram ports a session that ended is closing now: bound again only once closed
        self._unbinding: set[tuple[str, Address]] = set()
        self._unbound = threading.Condition(self._lock)

    def start(self) -> None: ...

    def wind_down(self) -> None:
        """The bridge stops: last words to the far side, before the counters are logged."""

    def stop(self) -> None:
        for route in self.router.snapshot():
            self.router.remove(route)

    def entries(self) -> list[TopicSpec | ServiceSpec]:
        """Topics, services, then the parts of actions."""
        plan = self.bridge.plan
        return [*plan.topics, *plan.services, *plan.action_parts]

    def initiate(self, connection: StreamConnection) -> StreamConnection:
        """The Noise handshake to the holder of ``server_key`` (or ``peer_key``)."""
        assert self.cfg.identity is not None and self.cfg.server_key is not None
        return initiate(connection, self.cfg.identity, self.cfg.server_key)

    def respond(self, connection: StreamConnection, host: str, known: Callable[[bytes], bool],
                admit: Callable[[], bool] | None = None) -> SecureConnection | None:
        """The responder's Noise handshake (``known``: whether a key is taken); None when it
        failed: closed, counted, said once per :data:`REFUSAL_EVERY` (keys cost nothing). A
        connection that completed it keeps its place in the connection limits for good."""
        assert self.cfg.identity is not None
        try:
            secure = respond(connection, self.cfg.identity, known, admit=admit)
        except HandshakeError as exc:
            connection.close()
            reason, sentence = self.handshake_refused(exc, host)
            self.router.link_drop(None, reason, f"from {host}")
            if sentence is not None:
                self.refusals.say(f"{reason} {host}", sentence)
            return None
        proven(connection)  # its place in the connection limits is never taken back
        return secure

    def handshake_refused(self, exc: HandshakeError, host: str) -> tuple[Reason, str | None]:
        """How a failed handshake is counted, and the sentence that says it (None: none); said
        by the roles that respond to handshakes (server, peer), never asked of a client."""
        raise NotImplementedError

    def sources(self, transport: Transport, host: str | None) -> Sources | None:
        """Who links of ``transport`` take frames from: ``bridge.allow`` when given, else
        ``host``; None (anyone) when the transport cannot tell who sent a frame."""
        if self.cfg.allow:
            return self.allow_list()
        hosts = transport.source_hosts(host or "")
        return None if hosts is None else Sources(hosts)

    def allow_list(self) -> Sources | None:
        """``bridge.allow`` as sources (None: anyone, when it is not given)."""
        return Sources((), map(str, self.cfg.allow)) if self.cfg.allow else None

    def read_control(self, frame: bytes, link: Link, source: Address) -> dict[str, Any] | None:
        """A control message on a line; None, counted, when unreadable."""
        message = parse_control(frame)
        if message is None:
            self.router.link_drop(link, Drop.BAD_CONTROL, f"from {source}")
            return None
        assert isinstance(link, StreamLink)
        link.last_heard = time.monotonic()
        return message

    def far_entries(self, routes: dict[int, Route], items: Any) -> None:
        """The far side's word (a hello's, a welcome's) on each entry: its type and QoS."""
        for index, route in routes.items():
            self.router.far(route, items[index] if isinstance(items, list)
                            and index < len(items) else None)

    def heartbeat(self, link: StreamLink | None) -> None:
        """Ping on a line, or fail it when silent for ``peer_timeout`` (a stalled TCP connection
        never ends alone)."""
        if link is None or link.closed.is_set():
            return
        silence = time.monotonic() - link.last_heard
        if silence > self.cfg.peer_timeout:
            link.fail(f"silent for {silence:.1f} s")
        else:
            link.send(control({"type": "ping"}), self.control)

    def _hold(self, kind: str, transport: Transport, local: Address, owner: object) -> None:
        if owner is not None:
            self._holders.setdefault((kind, transport.name, local), set()).add(id(owner))

    def release(self, owner: object) -> None:
        """Close every datagram link and listener that only ``owner`` held (a session that
        ended): its port is free again, its threads gone."""
        closing: list[tuple[DatagramLink | Acceptor, tuple[str, Address]]] = []
        with self._lock:
            for key, owners in list(self._holders.items()):
                owners.discard(id(owner))
                if owners:
                    continue
                del self._holders[key]
                where = key[1:]
                found = self.datagram_links if key[0] == "datagram" else self.listening
                item = found.pop(where, None)
                if isinstance(item, DatagramLink):
                    self.bare_ports.pop(item, None)
                    self._unbinding.add(where)
                if item is not None:
                    closing.append((item, where))
        for item, where in closing:
            item.close()
            self.life.forget(item)
            if isinstance(item, DatagramLink):
                with self._unbound:
                    self._unbinding.discard(where)
                    self._unbound.notify_all()

    def datagram_link(self, transport: Transport, local: Address, key: str = "bridge",
                      bare_named: bool | None = None, sources: Sources | None = None,
                      owner: object = None) -> DatagramLink:
        """The link bound at ``local``, shared by every entry on that port (the first decides
        its ``sources``). ``bare_named``: a port of ``framing: none`` topics, whether their
        datagrams carry names. An ``owner`` holds it until :meth:`release`, else the bridge."""
        assert isinstance(transport, DatagramTransport)
        with self._lock:
            # a session that just ended may still be closing this port (a client that came back
            # at once): bind once it is closed, not into "address already in use"
            self._unbound.wait_for(lambda: (transport.name, local) not in self._unbinding,
                                   UNBIND_WAIT)
            self._hold("datagram", transport, local, owner)
            found = self.datagram_links.get((transport.name, local))
            if found is not None:
                return found
            try:
                endpoint = transport.bind(local)
            except LinkError as exc:
                raise self.bridge.link_error(exc, key) from None
            name = f"{transport.name}:{local[1]}" if local[1] else f"{transport.name}"
            port = None if bare_named is None else self.router.bare_port(bare_named)
            link = DatagramLink(
                transport, endpoint, name, self.router.on_frame if port is None else port.on_frame,
                self.router.on_lost, bare=port is not None, sources=sources,
                budget=self.bridge.budget(transport),
                on_recovered=self.router.on_recovered if port is None else None,
                packetizers=self.bridge.resolver.plugins if port is None else None,
                hold_frames=self.cfg.queue_frames, hold_bytes=self.cfg.queue_bytes)
            if port is not None:
                self.bare_ports[link] = port
            self.datagram_links[(transport.name, local)] = self.life.closing(link)
            return link

    def accept(self, transport: Transport, local: Address,
               on_connection: Callable[[StreamConnection, Address], None], key: str | None,
               sources: Sources | None = None, name: str | None = None) -> Acceptor:
        """Accept stream connections at ``local`` within the connection limits, from ``sources``
        when given. A LinkError is located at ``key``, or raised when there is none."""
        assert isinstance(transport, StreamTransport)
        try:
            listener = transport.listen(local)
        except LinkError as exc:
            if key is None:
                raise
            raise self.bridge.link_error(exc, key) from None
        # a connection it closed at once is counted like a frame for no topic
        return self.life.closing(Acceptor(listener, name or f"{transport.name}:{local[1]}",
                                          on_connection, self.limits, sources,
                                          self.router.link_drop))

    def listen(self, transport: Transport, local: Address, on_frame: FrameHandler,
               key: str | None = None, handshake: Handshake | None = None,
               sources: Sources | None = None, untrusted: Untrusted | None = None,
               owner: object = None) -> Acceptor:
        """A link feeding ``on_frame`` for each connection accepted at ``local`` (one acceptor
        per address, held by ``owner`` until :meth:`release`), after ``handshake`` when given,
        held to ``untrusted`` until ``on_frame`` trusts it."""
        life, budget = self.life, self.bridge.budget(transport)

        def accepted(connection: StreamConnection, peer: Address) -> None:
            def link(ready: StreamConnection) -> None:
                life.closing(StreamLink(ready, f"{transport.name}:{local[1]}<-{peer[0]}", peer,
                                        on_frame, self.router.on_lost, on_close=life.forget,
                                        untrusted=untrusted, budget=budget))
            if handshake is None:
                link(connection)
            else:
                handshake(connection, peer, link)

        with self._lock:
            self._hold("listen", transport, local, owner)
            found = self.listening.get((transport.name, local))
            if found is None:
                found = self.listening[(transport.name, local)] = self.accept(
                    transport, local, accepted, key, sources)
            return found


@dataclass(eq=False)  # hashed by identity, as every sender
class Control:
    """The sender of control frames (topic 0: hellos, pings, the handshake); a dropped one
    belongs to no topic."""

    router: Router
    topic_id = envelope.CONTROL_TOPIC
    delivery = CONTROL  # the scheduler's class above every topic's: hellos and pings keep flowing

    def drop(self, reason: Reason, detail: str = "") -> None:
        self.router.link_drop(None, reason, detail or "a control frame on a link")

    def on_wire(self, size: int, again: bool) -> None:
        pass


class Refusals(Warner):
    """Refusals said once per window each (an attacker retrying must not flood the log)."""

    def say(self, key: str, message: str, level: int = logging.WARNING) -> None:
        held = self.due(key, "refused")
        if held is not None:
            log.log(level, "%s%s", message, f" ({held} more since)" if held else "")


class Answer:
    """The control message an initiator waits for on its new line (a welcome, a peer's keys)."""

    def __init__(self) -> None:
        self.message: dict[str, Any] | None = None
        self.got = threading.Event()  # cleared before each hello: a message is then new

    def put(self, message: dict[str, Any]) -> None:
        self.message = message
        self.got.set()

    def wait(self, link: StreamLink, stopping: threading.Event,
             timeout: float) -> dict[str, Any] | None:
        """The answer; None when the line closed, the bridge stops or ``timeout`` passed."""
        deadline = time.monotonic() + timeout
        while not self.got.wait(0.1):
            if link.closed.is_set() or stopping.is_set() or time.monotonic() > deadline:
                return None
        return self.message


def session_keys(schedule: KeySchedule, p: TopicSpec | ServiceSpec, name: str, send: str,
                 receive: str) -> SessionKeys:
    """An entry's keys in a session: ``name`` as both sides spell it, ``send`` and ``receive``
    the ways (``c2s``, ``s2c``; ``i2r``, ``r2i`` between peers)."""
    assert p.cipher_cls is not None
    return SessionKeys(schedule, p.cipher_cls, key_label(p.kind, send, name),
                       key_label(p.kind, receive, name))

