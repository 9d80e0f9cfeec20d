"""The peer role: both files complete, no main line.

A topic's id on the wire is derived from its link name (``remote``), so both sides agree without
talking. Receiving entries bind (or listen at) ``listen:port``; transmitting entries send (or
connect) to ``peer:port``. Services likewise: a serving side answers on the link and to the
address each call came from.

Entries on a bus (zenoh) are wired by :class:`~rosgate.roles.bus.BusWiring`: by key, without
ports or a far host.

Microcontrollers (the CVRA profile) are peers too: ``framing: none`` topics share a
:class:`~rosgate.routes.BarePort` per port, told apart by name, and ``framing:
serial_datagram`` services get a :class:`~rosgate.cvra.CallServer` per port (receive) or a
connection per call (transmit).
"""

from __future__ import annotations

from ..config import Direction, Framing
from ..cvra import CallServer
from ..errors import LinkError
from ..links import Acceptor, Connector, Link
from ..resolver import PreparedService, PreparedTopic
from ..router import fixed
from ..routes import ReceiveRoute
from ..services import ServerRoute
from ..transport import Address
from ..wire.envelope import topic_id_for
from . import NoLink, Role
from .bus import BusWiring


class PeerRole(Role):
    def start(self) -> None:
        bus = BusWiring(self.bridge)
        for p in self.bridge.plan.topics:
            if p.key is not None:
                bus.topic(p)
            elif p.transport.stream:
                self._stream_topic(p)
            else:
                self._datagram_topic(p)
        call_servers: dict[Address, CallServer] = {}
        for s in self.bridge.plan.services:
            if s.key is not None:
                bus.service(s)
            elif s.config.framing is Framing.SERIAL_DATAGRAM:
                self._microcontroller_service(s, call_servers)
            else:
                self._service(s)

    def _datagram_topic(self, p: PreparedTopic) -> None:
        t, key = p.config, f"topics[{p.index}].port"
        if t.direction is Direction.TRANSMIT:
            link = self.datagram_link(p.transport, p.local, key)
            self.router.topic(p, topic_id_for(t.remote), t.topic, link, fixed(p.address))
            return
        if t.framing is Framing.NONE:
            named = p.codec_cls.messagepack
            link = self.datagram_link(p.transport, p.address, key, bare_named=named)
            route = self.router.topic(p, topic_id_for(t.remote), t.topic, link)
            assert isinstance(route, ReceiveRoute)
            self.bare_ports[link].add(route, {t.topic, t.remote})
            return
        link = self.datagram_link(p.transport, p.address, key)
        self._receiver(p, link)

    def _stream_topic(self, p: PreparedTopic) -> None:
        t, key = p.config, f"topics[{p.index}].port"
        if t.direction is Direction.RECEIVE:
            self._receiver(p, NoLink())
            self.listen(p.transport, p.address, self.router.on_frame, key)
            return
        slot = self.bridge.slot(f"{t.transport}->{self.cfg.peer}:{t.port}")
        self.router.topic(p, topic_id_for(t.remote), t.topic, slot)
        Connector(p.transport, p.address, slot, self.router.on_frame, self.router.on_lost,
                  self.life, self.bridge.backoff).start()

    def _receiver(self, p: PreparedTopic, link: Link) -> None:
        """A receiving topic is found by its remote name's id, and by its own name's."""
        t = p.config
        route = self.router.topic(p, topic_id_for(t.remote), t.topic, link)
        assert isinstance(route, ReceiveRoute)
        if t.topic != t.remote:
            self.router.alias(route, topic_id_for(t.topic))

    def _service(self, p: PreparedService) -> None:
        """A service with an envelope: found by the id of its remote name."""
        s, key = p.config, f"services[{p.index}].port"
        service_id = topic_id_for(s.remote)
        link: Link
        if s.direction is Direction.RECEIVE:
            if p.transport.stream:
                self.listen(p.transport, p.address, self.router.on_frame, key)
                link = NoLink()  # answers go back on the connection each call came on
            else:
                link = self.datagram_link(p.transport, p.address, key)
        elif p.transport.stream:
            link = slot = self.bridge.slot(f"{s.transport}->{self.cfg.peer}:{s.port}")
            Connector(p.transport, p.address, slot, self.router.on_frame, self.router.on_lost,
                      self.life, self.bridge.backoff).start()
        else:
            link = self.datagram_link(p.transport, p.local, key)
        self.router.service(p, service_id, s.service, link, fixed(p.address))

    def _microcontroller_service(self, p: PreparedService,
                                 servers: dict[Address, CallServer]) -> None:
        """``framing: serial_datagram``: one connection per call. A serving port is shared by
        every service on it, told apart by name."""
        s = p.config
        if s.direction is Direction.TRANSMIT:
            self.router.service(p, 0, s.service, None)  # connects to the peer per call
            return
        if p.address not in servers:
            try:
                listener = p.transport.listen(p.address)
            except LinkError as exc:
                raise self.bridge.link_error(exc, f"services[{p.index}].port") from None
            server = servers[p.address] = CallServer(f"{p.transport.name}:{p.address[1]}",
                                                     self.router.link_drop)
            self.life.closing(Acceptor(listener, server.name, server.accepted))
        route = self.router.service(p, 0, s.service, None)  # found by name: no id
        assert isinstance(route, ServerRoute)
        servers[p.address].add(route)
