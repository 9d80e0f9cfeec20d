"""The peer role: both files complete, no main line.

A topic's id on the wire is derived from its link name (``remote``), so both sides agree without
talking. Receiving entries bind (or listen at) ``listen:port``; transmitting entries send (or
connect) to ``peer:port``. Services likewise: a serving side answers on the link and to the
address each call came from.

Entries on a bus (zenoh) are wired by :class:`~rosgate.roles.bus.BusWiring`: by key, without
ports or a far host (and with the file's static ciphers: a bus has no peer to handshake with).

Microcontrollers (the CVRA profile) are peers too: ``framing: none`` topics share a
:class:`~rosgate.routes.BarePort` per port, told apart by name, and ``framing:
serial_datagram`` services (the plugin ``rosgate-mcu-cvra``, through the
``rosgate_service_framings`` hook) get a :class:`~rosgate.service_framing.CallPort` per port
(receive) or a connection per call (transmit).

Peers with identities (``identity``, ``peer_key``, ``handshake_port``) run the client/server
handshake between them (:mod:`rosgate.secure`, Noise IK) on a TCP line of its own: the side
whose public key sorts first initiates (connects to ``peer:handshake_port``), the other
responds (listens on ``listen:handshake_port``) and sends the session's secret inside it.
Every ``framing: rosgate`` entry is then keyed from the session by its link name (``remote``,
which both files must spell alike), per direction and key generation; the line carries
heartbeats and is made again after a loss or a restart, with a new secret each time. Bare and
serial-datagram entries (microcontrollers) stay keyless.

Liveness: calls waiting for the far side's answers (an action's result waits up to an hour)
fail at once, counted ``link_down``, when the peer is lost, as a client's do when its main line
is: with identities, when the handshake line is (silent for ``peer_timeout``); without, when
the peer says nothing for :func:`silent_for` seconds — no announcement of any of its entries
(each says its type every :data:`~rosgate.announce.ANNOUNCE_EVERY` seconds) and no data. A
peer never heard from is not judged (an older rosgate announces nothing; its calls wait out
their timeouts). While it stays silent, each new call fails within ``heartbeat`` seconds.

Sources: every datagram link and listening stream port (the handshake line's too) takes frames
and connections only from ``bridge.peer`` (resolved once, at start), or, when it is given, from
the addresses of ``bridge.allow``; the others are counted ``not_allowed``, before any
reassembly. A microcontroller service port takes calls from anyone unless ``bridge.allow`` is
given. Transports that cannot tell who sent a frame (a CAN bus) filter nothing.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Any

from ..admission import Acceptor, Sources
from ..announce import ANNOUNCE_EVERY
from ..config import Direction, Framing
from ..drops import Drop
from ..errors import LinkError
from ..keyring import Keys
from ..links import Link
from ..router import fixed
from ..routes import ReceiveRoute, Route
from ..secure import (
    HandshakeError,
    KeySchedule,
    SecureConnection,
    SessionKeys,
    UnknownKey,
    initiate,
    respond,
)
from ..service_framing import CallPort
from ..services import CallerRoute, ServerRoute
from ..spec import ServiceSpec, TopicSpec
from ..streamlink import Connector, StreamLink
from ..transport import Address, StreamConnection, StreamTransport
from ..wire.envelope import topic_id_for
from . import NoLink, Refusals, Role
from .bus import BusWiring
from .mainline import control, is_control, key_label, parse_control

log = logging.getLogger("rosgate")

#: announcement periods a peer without a handshake line may stay silent before it is lost: one
#: announcement may be lost on the way, and a half period is the margin
SILENT_PERIODS = 2.5


def silent_for(peer_timeout: float) -> float:
    """Seconds of silence after which a peer without a handshake line is lost."""
    return max(peer_timeout, SILENT_PERIODS * ANNOUNCE_EVERY)


class PeerRole(Role):
    def __init__(self, bridge: Any):
        super().__init__(bridge)
        self.handshake: PeerHandshake | None = PeerHandshake(self) if self.cfg.secure else None
        #: the routes whose far side is the peer: what it says keeps it alive; callers wait on it
        self.heard_from: list[Route] = []
        self.callers: list[CallerRoute] = []
        self.lost = False  # a peer without a handshake line: silent too long

    def _keys(self, p: TopicSpec | ServiceSpec) -> Keys | None:
        """A session's keys for an entry with an envelope (None: the file's cipher)."""
        if self.handshake is None or p.config.framing is not Framing.ROSGATE:
            return None
        return self.handshake.keys(p)

    def _sources(self, p: TopicSpec | ServiceSpec) -> Sources | None:
        return self.sources(p.transport, self.cfg.peer)

    def start(self) -> None:
        if self.handshake is not None:
            self.handshake.start()
        self._start_entries()
        if self.handshake is None and self.callers and self.heard_from:
            threading.Thread(target=self._watch_peer, name="peer-liveness", daemon=True).start()

    def fail_calls(self, detail: str) -> None:
        """The peer is lost: every call waiting for its answer fails now."""
        for route in self.callers:
            route.fail_all(Drop.LINK_DOWN, detail)

    def last_heard(self) -> float | None:
        """When the peer last said anything of its entries (None: never)."""
        heard = [r.check.heard_at for r in self.heard_from if r.check.heard_at is not None]
        if not heard:
            return None
        data = [r.last_received for r in self.heard_from if isinstance(r, ReceiveRoute)
                and r.counters.received]
        return max(heard + data)

    def _watch_peer(self) -> None:
        """A peer without a handshake line: lost after :func:`silent_for` seconds of silence."""
        limit = silent_for(self.cfg.peer_timeout)
        while not self.life.stopping.wait(self.cfg.heartbeat):
            heard = self.last_heard()
            if heard is None:
                continue
            silence = time.monotonic() - heard
            if silence <= limit:
                if self.lost:
                    self.lost = False
                    log.info("%s: peer %s heard again", self.cfg.name, self.cfg.peer)
                continue
            if not self.lost:
                self.lost = True
                log.warning("%s: peer %s silent for %.1f s: taken for lost, calls waiting for "
                            "it fail", self.cfg.name, self.cfg.peer, silence)
            self.fail_calls(f"the peer {self.cfg.peer} was silent for {silence:.1f} s")

    def stop(self) -> None:
        super().stop()
        if self.handshake is not None:
            self.handshake.schedule.forget()

    def _start_entries(self) -> None:
        bus = BusWiring(self.bridge)
        for p in self.bridge.plan.topics:
            if p.key is not None:
                bus.topic(p)
            elif isinstance(p.transport, StreamTransport):
                self._stream_topic(p)
            else:
                self._datagram_topic(p)
        call_servers: dict[Address, CallPort] = {}
        for s in self.bridge.plan.services:
            if s.key is not None:
                bus.service(s)
            elif s.service_framing is not None:
                self._microcontroller_service(s, call_servers)
            else:
                self._service(s)
        for part in self.bridge.plan.action_parts:  # an action: three services, two topics
            if part.key is not None:
                bus.topic(part) if isinstance(part, TopicSpec) else bus.service(part)
            elif isinstance(part, ServiceSpec):
                self._service(part)
            elif isinstance(part.transport, StreamTransport):
                self._stream_topic(part)
            else:
                self._datagram_topic(part)

    def _datagram_topic(self, p: TopicSpec) -> None:
        t, key = p.config, f"topics[{p.index}].port"
        sources = self._sources(p)
        if t.direction is Direction.TRANSMIT:
            link = self.datagram_link(p.transport, p.local, key, sources=sources)
            self.router.topic(p, topic_id_for(t.remote), t.topic, link, fixed(p.address),
                              self._keys(p))
            return
        if t.framing is Framing.NONE:
            named = p.codec_cls.messagepack
            link = self.datagram_link(p.transport, p.address, key, bare_named=named,
                                      sources=sources)
            route = self.router.topic(p, topic_id_for(t.remote), t.topic, link)
            assert isinstance(route, ReceiveRoute)
            self.bare_ports[link].add(route, {t.topic, t.remote})
            return
        link = self.datagram_link(p.transport, p.address, key, sources=sources)
        self._receiver(p, link)

    def _stream_topic(self, p: TopicSpec) -> None:
        t, key = p.config, f"topics[{p.index}].port"
        if t.direction is Direction.RECEIVE:
            self._receiver(p, NoLink())
            self.listen(p.transport, p.address, self.router.on_frame, key,
                        sources=self._sources(p))
            return
        slot = self.bridge.slot(f"{t.transport}->{self.cfg.peer}:{t.port}")
        self.router.topic(p, topic_id_for(t.remote), t.topic, slot, keys=self._keys(p))
        Connector(p.transport, p.address, slot, self.router.on_frame, self.router.on_lost,
                  self.life, self.bridge.backoff, budget=self.bridge.budget(p.transport)).start()

    def _receiver(self, p: TopicSpec, link: Link) -> None:
        """A receiving topic is found by its remote name's id, and by its own name's."""
        t = p.config
        route = self.router.topic(p, topic_id_for(t.remote), t.topic, link, keys=self._keys(p))
        assert isinstance(route, ReceiveRoute)
        route.check.expect(route.drop)  # its sender may have announced before this side started
        self.heard_from.append(route)
        if t.topic != t.remote:
            self.router.alias(route, topic_id_for(t.topic))

    def _service(self, p: ServiceSpec) -> None:
        """A service with an envelope: found by the id of its remote name."""
        s, key = p.config, f"services[{p.index}].port"
        service_id = topic_id_for(s.remote)
        link: Link
        if s.direction is Direction.RECEIVE:
            if isinstance(p.transport, StreamTransport):
                self.listen(p.transport, p.address, self.router.on_frame, key,
                        sources=self._sources(p))
                link = NoLink()  # answers go back on the connection each call came on
            else:
                link = self.datagram_link(p.transport, p.address, key, sources=self._sources(p))
        elif isinstance(p.transport, StreamTransport):
            link = slot = self.bridge.slot(f"{s.transport}->{self.cfg.peer}:{s.port}")
            Connector(p.transport, p.address, slot, self.router.on_frame, self.router.on_lost,
                      self.life, self.bridge.backoff,
                      budget=self.bridge.budget(p.transport)).start()
        else:
            link = self.datagram_link(p.transport, p.local, key, sources=self._sources(p))
        route = self.router.service(p, service_id, s.service, link, fixed(p.address),
                                    self._keys(p))
        if isinstance(route, ServerRoute):  # its caller may have announced before it started
            route.check.expect(route.drop)
            self.heard_from.append(route)
        elif isinstance(route, CallerRoute):
            self.callers.append(route)

    def _microcontroller_service(self, p: ServiceSpec,
                                 servers: dict[Address, CallPort]) -> None:
        """``framing: serial_datagram`` (or another plugin's call pattern): one connection per
        call. A serving port is shared by every service on it, told apart by name."""
        s = p.config
        if s.direction is Direction.TRANSMIT:
            self.router.service(p, 0, s.service, None)  # connects to the peer per call
            return
        if p.address not in servers:
            assert isinstance(p.transport, StreamTransport)  # the resolver checked
            try:
                listener = p.transport.listen(p.address)
            except LinkError as exc:
                raise self.bridge.link_error(exc, f"services[{p.index}].port") from None
            assert p.service_framing is not None
            server = servers[p.address] = p.service_framing.server(
                f"{p.transport.name}:{p.address[1]}", self.router.link_drop,
                self.cfg.limits.idle_timeout)
            self.life.closing(Acceptor(listener, server.name, server.accepted, self.limits,
                                       self.allow_list(), self.refuse_connection))
        route = self.router.service(p, 0, s.service, None)  # found by name: no id
        assert isinstance(route, ServerRoute)
        servers[p.address].add(route)


class PeerHandshake:
    """The handshake line between two peers with identities, and the session's keys."""

    def __init__(self, role: PeerRole):
        cfg = role.cfg
        assert cfg.identity is not None and cfg.server_key is not None
        assert cfg.handshake_port is not None
        from ..identity import public_of

        self.role = role
        self.cfg = cfg
        self.identity, self.peer_key = cfg.identity, cfg.server_key
        self.initiator = public_of(cfg.identity) < cfg.server_key
        self.mine, self.theirs = ("i2r", "r2i") if self.initiator else ("r2i", "i2r")
        self.schedule = KeySchedule(cfg.rekey)
        self.refusals = Refusals()
        transport = role.bridge.resolver.transport("tcp", "bridge.handshake_port")
        assert isinstance(transport, StreamTransport)
        self.transport = transport
        self.key_id: int | None = None
        self.up = threading.Event()
        self.link: StreamLink | None = None
        self._answer: dict[str, Any] | None = None
        self._answered = threading.Event()

    def keys(self, p: TopicSpec | ServiceSpec) -> Keys:
        assert p.cipher_cls is not None
        kind = "topic" if isinstance(p, TopicSpec) else "service"
        name = p.config.remote
        return SessionKeys(self.schedule, p.cipher_cls, key_label(kind, self.mine, name),
                           key_label(kind, self.theirs, name))

    def _address(self, host: str | None) -> Address:
        try:
            return self.transport.check_address((host or "", self.cfg.handshake_port or 0))
        except ValueError as exc:
            raise self.cfg.error("bridge.handshake_port", str(exc)) from None

    def start(self) -> None:
        life = self.role.life
        if self.initiator:
            slot = self.role.bridge.slot(f"handshake->{self.cfg.peer}")
            Connector(self.transport, self._address(self.cfg.peer), slot, self._on_frame,
                      self.role.router.on_lost, life, self.role.bridge.backoff,
                      self._initiated, self._lost, secure=self._initiate).start()
        else:
            address = self._address(self.cfg.listen)
            try:
                listener = self.transport.listen(address)
            except LinkError as exc:
                raise self.role.bridge.link_error(exc, "bridge.handshake_port") from None
            role = self.role
            life.closing(Acceptor(listener, f"handshake:{address[1]}", self._accepted,
                                  role.limits, role.sources(self.transport, self.cfg.peer),
                                  role.refuse_connection))
        threading.Thread(target=self._ping_loop, name="peer-ping", daemon=True).start()

    # -- the initiator -------------------------------------------------------------------------
    def _initiate(self, connection: StreamConnection) -> StreamConnection:
        return initiate(connection, self.identity, self.peer_key)

    def _initiated(self, link: StreamLink) -> bool:
        """Wait for the responder's keys inside the new channel; install them."""
        self._answered.clear()
        self._answer = None
        deadline = time.monotonic() + 5.0
        while not self._answered.wait(0.1):
            if link.closed.is_set() or self.role.life.stopping.is_set():
                return False
            if time.monotonic() > deadline:
                log.warning("%s: no keys from peer %s", self.cfg.name, self.cfg.peer)
                return False
        answer = self._answer
        connection = link.connection
        try:
            assert answer is not None and isinstance(connection, SecureConnection)
            secret, key_id = bytes.fromhex(answer["secret"]), int(answer["key_id"])
            if len(secret) != 32 or not 0 <= key_id < 256:
                raise ValueError("not a session secret")
            if float(answer["rekey"]) != self.schedule.rekey:
                self.schedule.rekey = float(answer["rekey"])  # the responder's, as a server's
        except (AssertionError, KeyError, TypeError, ValueError) as exc:
            log.error("%s: cannot use the peer's keys: %s", self.cfg.name, exc)
            return False
        self.schedule.install(key_id, secret, connection.handshake_hash)
        link.send(control({"type": "ready", "key_id": key_id}), self.role.control)
        self._up(link)
        return True

    def _lost(self, link: StreamLink) -> None:
        self.up.clear()
        self.role.fail_calls("the handshake line with the peer was lost")
        log.warning("%s: peer %s down (%s); handshaking again", self.cfg.name, self.cfg.peer,
                    link.why or "handshake line closed")

    # -- the responder --------------------------------------------------------------------------
    def _accepted(self, connection: StreamConnection, peer: Address) -> None:
        def run() -> None:
            try:
                secure = respond(connection, self.identity, lambda key: key == self.peer_key)
            except HandshakeError as exc:
                connection.close()
                why = "its key is not peer_key" if isinstance(exc, UnknownKey) else str(exc)
                self.role.router.link_drop(None, Drop.BAD_HANDSHAKE, f"from {peer[0]}")
                self.refusals.say(f"{peer[0]}", f"{self.cfg.name}: refused a handshake "
                                  f"from {peer[0]}: {why}")
                return
            link = self.role.life.closing(StreamLink(
                secure, f"handshake<-{peer[0]}", peer, self._on_frame, self.role.router.on_lost,
                on_close=self._closed))
            first = self.key_id is None
            self.key_id = os.urandom(1)[0] if self.key_id is None else (self.key_id + 1) % 256
            secret = os.urandom(32)
            self.schedule.install(self.key_id, secret, secure.handshake_hash, seal_now=first)
            link.send(control({"type": "keys", "secret": secret.hex(), "key_id": self.key_id,
                               "rekey": self.schedule.rekey}), self.role.control)
            old, self.link = self.link, link
            if old is not None and old is not link:
                old.fail("the peer made a new handshake")
            self._up(link)

        threading.Thread(target=run, name=f"handshake-{peer[0]}", daemon=True).start()

    def _closed(self, link: StreamLink) -> None:
        self.role.life.forget(link)
        if link is self.link:
            self._lost(link)

    # -- both --------------------------------------------------------------------------------------
    def _up(self, link: StreamLink) -> None:
        self.link = link
        link.last_heard = time.monotonic()
        self.up.set()
        log.info("%s: peer %s up (authenticated)", self.cfg.name, self.cfg.peer)

    def _on_frame(self, frame: bytes, link: Link, source: Address) -> None:
        if not is_control(frame):
            self.role.router.link_drop(link, Drop.NOT_CONTROL,
                                       f"on the handshake line from {source}")
            return
        message = parse_control(frame)
        if message is None:
            self.role.router.link_drop(link, Drop.BAD_CONTROL, f"from {source}")
            return
        assert isinstance(link, StreamLink)
        link.last_heard = time.monotonic()
        if message["type"] == "keys" and self.initiator:
            self._answer = message
            self._answered.set()
        elif message["type"] == "ready" and not self.initiator:
            key_id = message.get("key_id")
            if isinstance(key_id, int):
                self.schedule.seal_with(key_id)

    def _ping_loop(self) -> None:
        cfg = self.cfg
        while not self.role.life.stopping.wait(cfg.heartbeat):
            link = self.link
            if not self.up.is_set() or link is None or link.closed.is_set():
                continue
            silence = time.monotonic() - link.last_heard
            if silence > cfg.peer_timeout:
                link.fail(f"silent for {silence:.1f} s")
            else:
                link.send(control({"type": "ping"}), self.role.control)
