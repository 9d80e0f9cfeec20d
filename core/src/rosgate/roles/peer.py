"""The peer role: both files complete, no main line. A topic's id is derived from its link name
(``remote``), so both sides agree without talking; receiving entries bind or listen at
``listen:port``, transmitting ones send or connect to ``peer:port``. Bus entries (zenoh) are
wired by their bus role (:mod:`rosgate.bus`); microcontroller entries (``framing: none``,
``serial_datagram``) share a :class:`~rosgate.routes.BarePort` or a
:class:`~rosgate.service_framing.CallPort` per port (docs/microcontrollers.md).

With identities, a TCP handshake line runs the client/server Noise handshake: the side whose
public key sorts first initiates, and ``framing: rosgate`` entries are keyed from its session
(docs/security.md). Calls waiting for the peer fail (``link_down``) when that line is lost, or,
without one, after :func:`silent_for` seconds without a word from the peer (docs/actions.md).
Links take frames only from ``bridge.peer`` or ``bridge.allow`` (``not_allowed``). Pattern
entries make their routes as names appear: :mod:`.peer_patterns`.
"""

from __future__ import annotations

import logging
import threading
import time

from ..announce import ANNOUNCE_EVERY
from ..bus import BusRole, BusTransport
from ..config import Direction, Framing
from ..datagram_stream import DatagramStream
from ..discovery import BusPattern
from ..drops import Drop, Reason
from ..errors import ConfigError, LinkError
from ..keyring import Keys, ReplayRecord, StaticKeys
from ..links.base import Link, NoLink
from ..links.datagram import DatagramLink
from ..router import fixed
from ..routes import ReceiveRoute, Route
from ..runtime import STATE_VARIABLE, private_folder, state_dir
from ..secure import HandshakeError, KeySchedule, SecureConnection, UnknownKey
from ..service_framing import CallPort, LineCallPort
from ..services import CallerRoute, ServerRoute
from ..spec import ServiceSpec, TopicSpec
from ..streamlink.connector import Connector
from ..streamlink.link import StreamLink
from ..transport import Address, DatagramTransport, StreamConnection, StreamTransport, Transport
from ..wire.envelope import is_control, topic_id_for
from . import Answer, Bridge, Role, session_keys
from .mainline import control
from .peer_patterns import PeerPatterns

log = logging.getLogger("rosgate")

#: announcement periods a peer without a handshake line may stay silent before it is lost: one
#: announcement may be lost, and a half period is the margin
SILENT_PERIODS = 2.5


def silent_for(peer_timeout: float) -> float:
    """Seconds of silence after which a peer without a handshake line is lost."""
    return max(peer_timeout, SILENT_PERIODS * ANNOUNCE_EVERY)


class PeerRole(Role):
    def __init__(self, bridge: Bridge):
        super().__init__(bridge)
        self.handshake: PeerHandshake | None = PeerHandshake(self) if self.cfg.secure else None
        #: the routes whose far side is the peer: what it says keeps it alive; callers wait on it
        self.heard_from: list[Route] = []
        self.callers: list[CallerRoute] = []
        self.lost = False  # a peer without a handshake line: silent too long
        self.bus_roles: dict[type[BusRole], BusRole] = {}
        #: the patterns: names found here, and names the peer announces
        self.discovery = PeerPatterns(self, self.keys_of, self.heard_from, self.callers,
                                      silent_for(self.cfg.peer_timeout))
        self.bus_patterns: list[BusPattern] = []  # pattern entries its bus roles watch for
        #: entries keyed by the file's key remember their peer's send times (made with the first)
        self.record: ReplayRecord | None = None
        self.remembered = True  # or a receiving entry keyed by the file starts without a record

    def start(self) -> None:
        if self.handshake is not None:
            self.handshake.start()
        self._start_entries()
        self.discovery.start()
        if not self.remembered and self.record is not None:
            why = f"unreadable: {self.record.unreadable}" if self.record.unreadable else \
                "a first start, or it was lost"
            log.warning("%s: no record of what peer %s sent before this start (%s, %s): frames "
                        "captured before now can be replayed to this bridge once each, until "
                        "its next restart (docs/security.md)", self.cfg.name, self.cfg.peer,
                        self.record.path, why)
        patterns_call = bool(self.discovery.taking["services"])  # their proxies come later
        if self.handshake is None and (self.callers and self.heard_from or patterns_call):
            threading.Thread(target=self._watch_peer, name="peer-liveness", daemon=True).start()

    def handshake_refused(self, exc: HandshakeError, host: str) -> tuple[Reason, str | None]:
        why = "its key is not peer_key" if isinstance(exc, UnknownKey) else str(exc)
        return Drop.BAD_HANDSHAKE, f"{self.cfg.name}: refused a handshake from {host}: {why}"

    def fail_calls(self, detail: str) -> None:
        for route in self.callers:
            route.fail_all(Drop.LINK_DOWN, detail)

    def last_heard(self) -> float | None:
        """When the peer last said anything of its entries (None: never: it is not judged)."""
        heard = [r.check.heard_at for r in self.heard_from if r.check.heard_at is not None]
        if not heard:
            return None
        data = [r.last_received for r in self.heard_from if isinstance(r, ReceiveRoute)
                and r.counters.received]
        return max(heard + data)

    def _watch_peer(self) -> None:
        limit = silent_for(self.cfg.peer_timeout)
        while not self.life.stopping.wait(self.cfg.heartbeat):
            heard = self.last_heard()
            if heard is None:
                continue
            silence = time.monotonic() - heard
            if silence > limit:
                if not self.lost:
                    log.warning("%s: peer %s silent for %.1f s: taken for lost, calls waiting "
                                "for it fail", self.cfg.name, self.cfg.peer, silence)
                self.lost = True
                self.fail_calls(f"the peer {self.cfg.peer} was silent for {silence:.1f} s")
            elif self.lost:
                self.lost = False
                log.info("%s: peer %s heard again", self.cfg.name, self.cfg.peer)

    def stop(self) -> None:
        self.discovery.stop()
        super().stop()
        if self.handshake is not None:
            self.handshake.schedule.forget()
        if self.record is not None:
            self.record.close()

    def _start_entries(self) -> None:
        call_servers: dict[Address, CallPort | LineCallPort] = {}
        for p in self.entries():
            if p.key is not None:  # one instance of each bus role per bridge
                assert isinstance(p.transport, BusTransport)
                cls = self.bridge.resolver.bus_role(p.transport, "")
                bus = self.bus_roles.get(cls) or self.bus_roles.setdefault(cls, cls(self.bridge))
                bus.topic(p) if isinstance(p, TopicSpec) else bus.service(p)
            elif isinstance(p, ServiceSpec) and p.service_framing is not None:
                self._microcontroller_service(p, call_servers)
            else:
                self._entry(p)
        for pattern in self.bridge.plan.patterns:  # a bus's, whose role finds what it announces
            if pattern.checked is not None and pattern.checked.key is not None:
                cls = self.bridge.resolver.bus_role(pattern.checked.transport, "")
                bus = self.bus_roles.get(cls) or self.bus_roles.setdefault(cls, cls(self.bridge))
                self.bus_patterns.append(BusPattern(self.cfg, pattern, self.bridge.resolver.found))
                bus.pattern(self.bus_patterns[-1])

    def _entry(self, p: TopicSpec | ServiceSpec) -> None:
        """An entry found by the id of its remote name (a receiving topic by its own name's
        too)."""
        c, key = p.config, f"{p.kind}s[{p.index}].port"
        stream = isinstance(p.transport, StreamTransport)
        sources = self.sources(p.transport, self.cfg.peer)
        bare = None  # a port of framing: none topics: whether their datagrams carry names
        link: Link
        if c.direction is Direction.RECEIVE and stream:
            link = NoLink()  # frames come through the listener; answers go back on their line
        elif c.direction is Direction.RECEIVE:
            bare = p.codec_cls.messagepack if c.framing is Framing.NONE else None
            link = self.datagram_link(p.transport, p.address, key, bare, sources)
        elif stream:
            link = slot = self.bridge.slot(f"{c.transport}->{self.cfg.peer}:{c.port}")
        else:
            link = self.datagram_link(p.transport, p.local, key, sources=sources)
        route = self.router.route(p, topic_id_for(c.remote), p.name, link, fixed(p.address),
                                  self.keys_of(p))
        if stream and c.direction is Direction.RECEIVE:
            self.listen(p.transport, p.address, self.router.on_frame, key, sources=sources)
        elif stream:
            Connector(p.transport, p.address, slot, self.router.on_frame, self.router.on_lost,
                      self.life, self.bridge.backoff,
                      budget=self.bridge.budget(p.transport)).start()
        if isinstance(route, CallerRoute):
            self.callers.append(route)
        elif bare is not None:  # framing: none, told apart by name
            assert isinstance(route, ReceiveRoute) and isinstance(link, DatagramLink)
            self.bare_ports[link].add(route, {p.name, c.remote})
            if self._line_calls(p.transport):
                self.bare_ports[link].leave_calls()
        elif isinstance(route, ReceiveRoute | ServerRoute):
            route.check.expect(route.drop)  # its sender may have announced before it started
            self.heard_from.append(route)
            if p.name != c.remote and isinstance(route, ReceiveRoute):
                self.router.alias(route, topic_id_for(p.name))

    def keys_of(self, p: TopicSpec | ServiceSpec, name: str | None = None) -> Keys | None:
        """An entry's keys: a session's, or the file's key with the replay record (None: the
        file's cipher as it is); ``name``: keys of that name on the entry's link (default: its
        remote)."""
        c = p.config
        if self.handshake is not None and c.framing is Framing.ROSGATE:
            return self.handshake.keys(p, name)
        if c.framing is Framing.ROSGATE and p.cipher is not None and p.cipher.authenticates:
            if c.direction is Direction.RECEIVE and not self._record().known:
                self.remembered = False
            return StaticKeys(p.cipher, self._record())
        return None

    def _line_calls(self, transport: Transport) -> bool:
        """Whether microcontroller calls share ``transport``'s line with its bare topics."""
        return any(isinstance(s, ServiceSpec) and s.service_framing is not None
                   and s.transport is transport for s in self.entries())

    def _record(self) -> ReplayRecord:
        """The bridge's replay record, ``<state folder>/<name>.replay`` (read on first use;
        :class:`~rosgate.runtime.NotPrivate` when another user could write there)."""
        if self.record is None:
            try:
                folder = private_folder(state_dir(), STATE_VARIABLE)
                self.record = ReplayRecord(folder / f"{self.cfg.name}.replay")
            except OSError as exc:
                raise ConfigError(f"no replay record for the key file's entries: {exc}",
                                  file=self.cfg.file, fix=f"set {STATE_VARIABLE} to a folder "
                                  "of this user's alone, on storage that survives a reboot "
                                  "(one per bridge of this name)") from None
        return self.record

    def _microcontroller_service(self, p: ServiceSpec,
                                 servers: dict[Address, CallPort | LineCallPort]) -> None:
        """``framing: serial_datagram`` (or another plugin's call pattern): a connection per call;
        a serving port is shared by its services, told apart by name (no id), and takes calls
        from anyone unless ``bridge.allow`` is given."""
        s = p.config
        if s.direction is Direction.TRANSMIT:
            self.router.service(p, 0, s.service, None)  # connects to the peer per call
            return
        assert p.service_framing is not None
        if isinstance(p.transport, DatagramTransport) and p.address not in servers:  # a line
            try:
                servers[p.address] = self.life.closing(p.service_framing.line_server(
                    f"{p.transport.name}:{p.address[1]}", self.router.link_drop, p.transport,
                    p.address))
            except LinkError as exc:
                raise self.bridge.link_error(exc, f"services[{p.index}].port") from None
        if p.address not in servers:
            server = servers[p.address] = p.service_framing.server(
                f"{p.transport.name}:{p.address[1]}", self.router.link_drop,
                self.cfg.limits.idle_timeout)
            self.accept(p.transport, p.address, server.accepted, f"services[{p.index}].port",
                        self.allow_list())
        route = self.router.service(p, 0, s.service, None)
        assert isinstance(route, ServerRoute)
        servers[p.address].add(route)


class PeerHandshake:
    """The handshake line between two peers with identities, and the session's keys."""

    def __init__(self, role: PeerRole):
        cfg = self.cfg = role.cfg
        assert cfg.identity and cfg.server_key and cfg.handshake_port is not None
        from ..identity import public_of

        self.role = role
        self.initiator = public_of(cfg.identity) < cfg.server_key
        self.mine, self.theirs = ("i2r", "r2i") if self.initiator else ("r2i", "i2r")
        self.schedule = KeySchedule(cfg.rekey)
        transport = role.bridge.resolver.transport(cfg.handshake_line, "bridge.handshake_line")
        if isinstance(transport, DatagramTransport):  # the line is all there is (serial)
            transport = DatagramStream(transport)
        elif not isinstance(transport, StreamTransport):
            raise cfg.error("bridge.handshake_line", f"{cfg.handshake_line} cannot carry a "
                            "handshake", fix="name a stream link (tcp) or a datagram link "
                            "between the two peers (serial, udp)")
        self.transport: StreamTransport = transport
        self.up = threading.Event()
        self.link: StreamLink | None = None
        self.answer = Answer()

    def keys(self, p: TopicSpec | ServiceSpec, name: str | None = None) -> Keys:
        return session_keys(self.schedule, p, name or p.config.remote, self.mine, self.theirs)

    def _address(self, host: str | None) -> Address:
        try:
            return self.transport.check_address((host or "", self.cfg.handshake_port or 0))
        except ValueError as exc:
            raise self.cfg.error("bridge.handshake_port", str(exc)) from None

    def start(self) -> None:
        if self.initiator:
            slot = self.role.bridge.slot(f"handshake->{self.cfg.peer}")
            Connector(self.transport, self._address(self.cfg.peer), slot, self._on_frame,
                      self.role.router.on_lost, self.role.life, self.role.bridge.backoff,
                      self._initiated, self._lost, secure=self._initiate).start()
        else:
            address = self._address(self.cfg.listen)
            self.role.accept(self.transport, address, self._accepted, "bridge.handshake_port",
                             self.role.sources(self.transport, self.cfg.peer),
                             f"handshake:{address[1]}")
        threading.Thread(target=self._ping_loop, name="peer-ping", daemon=True).start()

    # -- the initiator -------------------------------------------------------------------------
    def _initiate(self, connection: StreamConnection) -> StreamConnection:
        """The Noise handshake. The responder sends its keys as soon as it is done, unasked:
        they may be read before :meth:`_initiated` runs, so the last line's are forgotten here,
        before they can come (seen on a serial line, where a round trip is long)."""
        self.answer.got.clear()
        return self.role.initiate(connection)

    def _initiated(self, link: StreamLink) -> bool:
        """Wait for the responder's keys inside the new channel; install them."""
        answer = self.answer.wait(link, self.role.life.stopping, 5.0)
        if answer is None:
            if not link.closed.is_set() and not self.role.life.stopping.is_set():
                log.warning("%s: no keys from peer %s", self.cfg.name, self.cfg.peer)
            return False
        connection = link.connection
        assert isinstance(connection, SecureConnection)
        try:
            rekey = float(answer["rekey"])  # the responder's, as a server's
            key_id = self.schedule.accept(answer, connection.handshake_hash)
        except (KeyError, TypeError, ValueError) as exc:
            log.error("%s: cannot use the peer's keys: %s", self.cfg.name, exc)
            return False
        self.schedule.rekey = rekey
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
            secure = self.role.respond(connection, peer[0], lambda key: key == self.cfg.server_key)
            if secure is None:
                return
            link = self.role.life.closing(StreamLink(
                secure, f"handshake<-{peer[0]}", peer, self._on_frame, self.role.router.on_lost,
                on_close=self._closed))
            keys = self.schedule.offer(secure.handshake_hash)
            link.send(control({"type": "keys", **keys}), self.role.control)
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
        message = self.role.read_control(frame, link, source)
        if message is None:
            return
        if message["type"] == "keys" and self.initiator:
            self.answer.put(message)
        elif message["type"] == "ready" and not self.initiator:
            self.schedule.seal_with(message.get("key_id"))

    def _ping_loop(self) -> None:
        while not self.role.life.stopping.wait(self.cfg.heartbeat):
            if self.up.is_set():
                self.role.heartbeat(self.link)
