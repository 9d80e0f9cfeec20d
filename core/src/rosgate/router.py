"""The router owns every route of a running bridge: it makes them (with their ROS entities),
finds the route of every frame that comes in (topics, calls and answers by id, in tables of
their own) and counts what belongs to none. Roles choose links and ids; it never opens a link.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from . import announce, routestats
from .actions import ClientGoals
from .announce import Identity
from .config import BridgeConfig, Direction, Framing
from .drops import Drop, Reason
from .endpoints import Endpoints
from .errors import CipherError
from .holdback import Holdback
from .keyring import Keys, NoKey, StaticKeys
from .links.base import Link
from .proxies import Proxies
from .ros import RosNode, cdr_checker
from .rostypes import QOS_UNFOUND, type_hash
from .routes import (
    BareFraming,
    BarePort,
    Counters,
    EnvelopeFraming,
    ReceiveRoute,
    Route,
    TransmitRoute,
)
from .services import CallerRoute, Deadlines, ServerRoute, ServiceCodec, ServiceRoute, deep_qos
from .spec import ServiceSpec, TopicSpec
from .transport import Address, DatagramTransport, StreamTransport
from .warn import BUGS, Warner
from .wire import envelope
from .wire.names import Layout

log = logging.getLogger("rosgate")

#: seconds between looks at the publishers of topics without a qos (and announcements of young
#: entries)
WATCH_EVERY = announce.ANNOUNCE_FAST

Destination = Callable[[], Address | None]
HelloHandler = Callable[[envelope.Header, bytes, Link, Address], None]
#: (route, header, link, source): a topic's frame opened, on a datagram link, from that source
HeardHandler = Callable[[Route, envelope.Header, Link, Address], None]

#: the flags of frames that are not a topic's message
_NOT_DATA = (envelope.FLAG_HELLO | envelope.FLAG_REQUEST | envelope.FLAG_REPLY
             | envelope.FLAG_ANNOUNCE)


#: the most counters of removed routes kept for the routes that replace them
MAX_RETIRED = 10_000


def fixed(address: Address | None) -> Destination:
    """A destination that never changes (a configured peer, a server's port)."""
    return lambda: address


_no_destination = fixed(None)


def _anywhere(source: Address) -> bool:
    """Where a role that does not follow its far sides knows them to be: anywhere."""
    return True


class Router:
    def __init__(self, ros: RosNode, warner: Warner | None = None):
        self.ros = ros
        self.warner = warner or Warner()
        self.deadlines = Deadlines()
        self.receivers: dict[int, ReceiveRoute] = {}
        self.callers: dict[int, CallerRoute] = {}
        self.servers: dict[int, ServerRoute] = {}
        self.routes: list[Route] = []
        #: the counters of routes taken down, by kind and label, for the route that replaces
        #: one (a reconnect, a new policy, a QoS change): a bridge's counters only grow
        self._retired: dict[tuple[type, str], Counters] = {}
        self.link_drops: Counter = Counter()
        #: a role that takes hellos (the server) sets this; elsewhere a hello is foreign
        self.on_hello: HelloHandler | None = None
        #: a role that learns where its far sides are from their frames (the server) sets this,
        #: and ``known``, where they are known to be: a datagram frame a route took from
        #: anywhere else goes to ``on_heard`` (a far side that moved); from there, nowhere
        self.on_heard: HeardHandler | None = None
        self.known: Callable[[Address], bool] = _anywhere
        #: a role that learns names from announcements for no route yet (a peer's patterns)
        self.on_unknown_announcement: HelloHandler | None = None
        self._lock = threading.RLock()
        self._closing = threading.Event()
        #: makes the routes' subscriptions and publishers as the graph allows
        self.endpoints = Endpoints(ros, self._lock, self.announce)
        #: the proxies of mirrored services, as the far side's servers come and go
        self.proxies = Proxies(ros, self._lock, self.announce, lambda route: route in self.routes)
        self._watcher = threading.Thread(target=self._watch, name="announce", daemon=True)
        self._watcher.start()

    # -- making routes -----------------------------------------------------------------------
    def route(self, p: TopicSpec | ServiceSpec, route_id: int, label: str, link: Link,
              destination: Destination = _no_destination, keys: Keys | None = None,
              announce: bool = True, goals: ClientGoals | None = None,
              hold: Holdback | None = None, mirror: bool = False) -> Route:
        """The route of an entry over ``link``, a topic's or a service's, as its spec says.
        ``goals``: an action's part as one client of a server may use it; ``hold``: where a
        client's reliable messages wait while its server is out of reach; ``mirror``: below."""
        if isinstance(p, TopicSpec):
            return self.topic(p, route_id, label, link, destination, keys, announce=announce,
                              select=None if goals is None else goals.select, hold=hold)
        return self.service(p, route_id, label, link, destination, keys, announce, goals,
                            mirror=mirror)

    def topic(self, p: TopicSpec, topic_id: int, label: str, link: Link,
              destination: Destination = _no_destination,
              keys: Keys | None = None,
              bare_names: bool = True, announce: bool = True,
              select: Callable[[Any], Any] | None = None,
              hold: Holdback | None = None) -> TransmitRoute | ReceiveRoute:
        """A topic's route and its ROS entity. ``keys``: a session's (default: the file's cipher).
        ``hold``: where a transmitting topic's messages wait while the far side is out of reach.
        ``bare_names=False``: bare frames never carry the topic's name (a bus names them by key).
        ``announce=False``: announcements wait for :meth:`start_announcing` (a client's, until
        the server knows where its datagrams come from)."""
        t = p.config
        keys = keys or _file_keys(p)
        codec = p.codec_cls(p.msg_type, p.codec_options)
        qos = t.qos
        route: TransmitRoute | ReceiveRoute
        if t.direction is Direction.TRANSMIT:
            framing = (BareFraming(t.remote if codec.messagepack and bare_names else None,
                                   Layout(t.layout))
                       if t.framing is Framing.NONE else EnvelopeFraming())
            route = TransmitRoute(t, topic_id, codec, keys, self.warner, label, p.delivery,
                                  framing=framing, link=link, destination=destination,
                                  compression=p.compression, select=select, hold=hold)
            self._identify(route, p.msg_type)
            if not t.qos_given:
                route.qos_found = self.ros.qos_found(t.topic)
                qos = route.qos_in_use = route.qos_found or QOS_UNFOUND
            # announced before the first message, or a latched history
            self._start(route, announce and t.framing is Framing.ROSGATE)
            route.batches = self.ros.batches_of(p.delivery.real_time)
            self.endpoints.listen_when_heard(route)
        else:
            decode: Callable[[bytes], Any] = codec.decode
            if codec.raw and not (keys.authenticates and t.framing is Framing.ROSGATE):
                decode = _checked(decode, cdr_checker(p.msg_type))
            route = ReceiveRoute(t, topic_id, codec, keys, self.warner, label, p.delivery,
                                 decode=decode, transforms=p.transforms)
            self._identify(route, p.msg_type)
            route.qos_in_use = None if t.qos_given else QOS_UNFOUND
            self.endpoints.publish(route, qos)
        self._add(route, self.receivers if isinstance(route, ReceiveRoute)
                  and t.framing is Framing.ROSGATE else None, topic_id)
        return route

    def service(self, p: ServiceSpec, service_id: int, label: str, link: Link | None,
                destination: Destination = _no_destination,
                keys: Keys | None = None, announce: bool = True,
                goals: ClientGoals | None = None, mirror: bool = False) -> ServiceRoute:
        """A service's route and its ROS entity; found by id with an envelope (else by name).
        ``mirror`` (client/server): its proxy exists only while a real ROS server runs on the
        serving side (:mod:`rosgate.proxies`)."""
        s = p.config
        args = (s, service_id, ServiceCodec(p.codec_cls, p.srv_type, p.codec_options),
                keys or _file_keys(p), self.warner, label, p.srv_type, self.deadlines)
        qos = deep_qos()
        route: ServiceRoute
        mirror = mirror and s.framing is Framing.ROSGATE
        if s.direction is Direction.RECEIVE:
            served = mirror and bool(self.ros.served([s.service]))
            route = ServerRoute(*args, goals=goals, link=link if mirror else None,
                                destination=destination, served=served)
            self._identify(route, p.srv_type)
            route.entity = self.ros.client(p.srv_type, s.service, qos)
            if mirror:
                self._start(route, announce)
        elif p.service_framing is not None:  # a microcontroller's call pattern, by its plugin
            assert isinstance(p.transport, StreamTransport | DatagramTransport)  # as checked
            route = caller = p.service_framing.caller(*args, transport=p.transport,
                                                      address=p.address)
            route.entity = self.ros.deferred_service(p.srv_type, s.service, qos, caller.on_request)
        else:
            assert link is not None
            route = CallerRoute(*args, link=link, destination=destination, mirrored=mirror)
            self._identify(route, p.srv_type)
            self._start(route, announce)
            if not mirror:  # else once the far side says a real server runs there
                route.entity = self.proxies.make(route)
        table = self.servers if isinstance(route, ServerRoute) else self.callers
        self._add(route, table if s.framing is Framing.ROSGATE else None, service_id)
        return route

    def _add(self, route: Route, table: dict[int, Any] | None, route_id: int) -> None:
        """A new route, found by ``route_id`` in ``table`` (None: found otherwise, or never)."""
        with self._lock:
            carried = self._retired.pop((type(route), route.label), None)
            if carried is not None:
                route.counters = carried
            self.routes.append(route)
            if table is not None:
                table[route_id] = route

    def _start(self, route: Route, announces: bool) -> None:
        route.announces = announces
        if announces:
            self.announce(route)

    def _renew(self, route: TransmitRoute | ReceiveRoute, qos: dict[str, Any]) -> bool:
        """A route's subscription or publisher made anew with ``qos``, overlapping the old one.
        A publisher is renewed only for a new QoS; a subscription also to get a latched history
        again."""
        with self._lock:
            old = route.entity
            if old is None or isinstance(route, ReceiveRoute) and qos == route.qos_in_use:
                return False  # removed meanwhile, or done already
            if isinstance(route, TransmitRoute):
                self.endpoints.listen(route, qos)
            else:
                self.endpoints.publish(route, qos)
            route.qos_in_use = qos
        self.ros.destroy(old)
        return True

    def bare_port(self, named: bool) -> BarePort:
        return BarePort(named, self.link_drop)

    def alias(self, route: ReceiveRoute, topic_id: int) -> None:
        """Find ``route`` under a second id too (peer role: its own name besides its remote)."""
        with self._lock:
            self.receivers[topic_id] = route

    def renumber(self, route: Route, topic_id: int) -> None:
        """Give a route the id a restarted server chose for it."""
        with self._lock:
            tables = self._forget(route)
            route.topic_id = topic_id
            for table in tables:
                table[topic_id] = route

    def remove(self, route: Route) -> None:
        with self._lock:
            self._forget(route)
            if route in self.routes:
                self.routes.remove(route)
                if len(self._retired) < MAX_RETIRED:  # labels come from clients' entries
                    self._retired[(type(route), route.label)] = route.counters
        self.endpoints.forget(route)
        with self._lock:  # a mirrored proxy is made under it, and never for a removed route
            entity, route.entity = route.entity, None
        if entity is not None:
            self.ros.destroy(entity)
        route.close()

    def _forget(self, route: Route) -> list[dict[int, Any]]:
        """``route`` taken out of the dispatch tables (every id); the tables it was in."""
        tables = [t for t in (self.receivers, self.callers, self.servers) if route in t.values()]
        for table in tables:
            for i in [i for i, r in table.items() if r is route]:
                del table[i]
        return tables

    # -- receiving: every envelope frame from every link comes through here ----------------
    def on_frame(self, frame: bytes, link: Link, source: Address) -> None:
        try:
            header = envelope.unpack(frame)
        except envelope.EnvelopeError as exc:
            self.link_drop(link, exc.reason, f"{len(frame)} bytes from {source}")
            return
        flags, topic_id = header.flags, header.topic_id
        if not flags & _NOT_DATA:  # a topic's frame: the common case first
            route = self.receivers.get(topic_id)
            if route is None:
                self.link_drop(link, Drop.UNKNOWN_TOPIC, f"topic id {topic_id} from {source}")
            elif route.on_frame(header, frame, link.arrived) and link.datagram \
                    and self.on_heard is not None and not self.known(source):
                self.on_heard(route, header, link, source)
        elif flags & envelope.FLAG_HELLO:
            if self.on_hello is None:
                self.link_drop(link, Drop.UNEXPECTED_HELLO, f"from {source}")
            else:
                self.on_hello(header, frame, link, source)
        elif (calls := flags & envelope.FLAG_REQUEST) or not flags & envelope.FLAG_ANNOUNCE:
            service: Any = (self.servers if calls else self.callers).get(topic_id)
            if service is None:
                self.link_drop(link, Drop.UNKNOWN_SERVICE, f"service id {topic_id} from {source}")
            elif calls:
                service.on_request(header, frame, link, source)
            else:
                service.on_reply(header, frame)
        else:
            self._announced(header, frame, link, source)

    # -- what the sides say of their entries (rosgate.announce) ---------------------------------
    def hash_of(self, interface: type) -> str | None:
        """The RIHS01 hash of a message or service class (None: this ROS gives none)."""
        return type_hash(interface)

    def _identify(self, route: Route, interface: type) -> None:
        route.check.mine = Identity(route.entry.type, self.hash_of(interface))
        route.interface = interface

    def announce(self, route: Route) -> None:
        """Say the entry's type (and the QoS found here) on its link, to its far side."""
        link, to = route.link, route.destination()
        if to is None and link.datagram:
            return  # the far side's address is not known yet: the next announcement finds it
        try:
            frame = route.announcement()
        except (NoKey, CipherError):
            return  # not data: the next announcement comes soon
        link.send(frame, route.announcer, to)

    def _announced(self, header: envelope.Header, frame: bytes, link: Link,
                   source: Address) -> None:
        """A far side's announcement: to the receiving route (or serving route) of its id."""
        route: Route | None = (self.receivers.get(header.topic_id)
                               or self.servers.get(header.topic_id)
                               or self.callers.get(header.topic_id))
        if route is None:
            if self.on_unknown_announcement is not None:
                self.on_unknown_announcement(header, frame, link, source)
                return
            # an entry this side does not carry: on a shared bus (CAN) every node hears every
            # node's announcements. No message is lost, so no drop: said in debug
            log.debug("%s: an announcement for id %d from %s, an entry this side does not carry",
                      link.name, header.topic_id, source)
            return
        self._follow(route, route.heard(header, frame))

    def far(self, route: Route, item: Any) -> None:
        """What a hello or a welcome says of the far side's entry (None: nothing, an older
        rosgate): its type checked, its QoS or its server followed."""
        self._follow(route, route.told(item))

    def _follow(self, route: Route, said: tuple[Any, dict[str, Any] | None] | None) -> None:
        if isinstance(route, ReceiveRoute) and said is not None:
            self.follow_qos(route, said[1])
        elif isinstance(route, CallerRoute) and said is not None:
            self.proxies.follow(route)

    def entry_item(self, p: TopicSpec | ServiceSpec) -> dict[str, Any]:
        """An entry as a hello says it before its route exists (with the QoS found here for a
        topic it sends without a qos, whether a real server runs here for a service it
        serves)."""
        if isinstance(p, TopicSpec):
            t = p.config
            qos = (self.ros.qos_found(t.topic)
                   if t.direction is Direction.TRANSMIT and not t.qos_given else None)
            return announce.item(Identity(t.type, self.hash_of(p.msg_type)), qos)
        s, here = p.config, p.config.direction is Direction.RECEIVE
        served = bool(self.ros.served([s.service])) if here else None  # client/server: rosgate
        return announce.item(Identity(s.type, self.hash_of(p.srv_type)), None, served)

    def item(self, route: Route) -> dict[str, Any]:
        """This side's entry as a hello or a welcome says it."""
        return route.said()

    def follow_qos(self, route: ReceiveRoute, qos: dict[str, Any] | None) -> None:
        """The publisher takes the QoS the far side found from its publishers, unless the
        entry sets its own (a new publisher replaces the old)."""
        if route.topic.qos_given or qos is None or qos == route.qos_in_use:
            return
        if self._renew(route, qos):
            log.info("%s: publishes as its far side's publishers do: %s, %s, depth %d",
                     route.label, qos["reliability"], qos["durability"], qos["depth"])

    def start_announcing(self, routes: list[Route]) -> None:
        """Routes made with ``announce=False`` say their entries now, and from now on."""
        for route in routes:
            if (isinstance(route, TransmitRoute) and not route.delivery.whole
                    or isinstance(route, CallerRoute)
                    or isinstance(route, ServerRoute) and route.mirror):
                self._start(route, True)

    def resync(self, routes: list[Route] | None = None) -> None:
        """The far side (re)appeared: latched topics found here say their QoS again and
        subscribe anew, so it gets their history."""
        for route in self.snapshot() if routes is None else routes:
            if (isinstance(route, TransmitRoute) and route.qos_found is not None
                    and route.qos_found["durability"] == "transient_local"):
                self.announce(route)
                self._renew(route, route.qos_found)

    def _find_qos(self, route: TransmitRoute) -> None:
        """The publishers of a topic without a qos: a new QoS is announced, then subscribed."""
        found = self.ros.qos_found(route.topic.topic)
        if found is None or found == route.qos_found:
            return
        route.qos_found = found
        log.info("%s: subscribes as its publishers publish: %s, %s, depth %d", route.label,
                 found["reliability"], found["durability"], found["depth"])
        if route.announces:
            self.announce(route)
        if found != route.qos_in_use:  # a new subscription only for a new QoS (it overlaps)
            self._renew(route, found)

    def _watch(self) -> None:
        """Every :data:`WATCH_EVERY` seconds, the publishers of topics without a qos; every
        :data:`~rosgate.announce.ANNOUNCE_EVERY` seconds, every entry's announcement."""
        every = max(1, round(announce.ANNOUNCE_EVERY / WATCH_EVERY))
        for tick in itertools.count():
            if self._closing.wait(WATCH_EVERY):
                return
            now = time.monotonic()
            self.proxies.watch(self.snapshot())
            for route in self.snapshot():
                try:
                    if isinstance(route, TransmitRoute) and not route.topic.qos_given:
                        self._find_qos(route)
                    if route.check.awaiting:  # a far side that never says its type
                        route.check.expire(now)
                    young = now - route.born < announce.YOUNG
                    if route.announces and (young or tick % every == 0):
                        self.announce(route)
                except Exception:  # one route's trouble must not stop the others' announcements
                    BUGS.bug("announce_error", f"{route.label}: could not announce or look at "
                                               "its publishers (a bug: please report it)")

    def on_lost(self, topic_id: int | None, reason: Reason) -> None:
        """A receiving link lost a frame or met bytes it could not frame: counted against the
        topic when the link knows it."""
        route = self.receivers.get(topic_id) if topic_id is not None else None
        if route is not None:
            route.drop(reason)
        else:
            self.link_drop(None, reason, "on a link")

    def on_recovered(self, topic_id: int) -> None:
        """A receiving link rebuilt a frame from repair fragments or retransmissions."""
        route = self.receivers.get(topic_id)
        if route is not None:
            route.counters.recovered += 1

    def link_drop(self, link: Any, reason: Reason, detail: str) -> None:
        """A frame that belongs to no route: counted per bridge, warned about per link."""
        with self._lock:
            self.link_drops[reason] += 1
        self.warner.warn(link.name if link is not None else "link", reason, detail)

    # -- housekeeping: stale topics and statistics (rosgate.routestats) ------------------------
    def warn_stale(self, config: BridgeConfig, now: float) -> None:
        routestats.warn_stale(self.snapshot(), config, now)

    def snapshot(self) -> list[Route]:
        with self._lock:
            return list(self.routes)

    def stats(self) -> dict[str, Any]:
        """Counters per route, plus drops that belong to no topic."""
        return routestats.stats(self.snapshot(), self.link_drops)

    def log_stats(self, routes: list[Route] | None = None) -> None:
        """Log the counters of ``routes`` (default: every route, and the frames for no topic)."""
        routestats.log_stats(self.snapshot() if routes is None else routes,
                             self.link_drops if routes is None else None)

    def close(self) -> None:
        self._closing.set()
        self._watcher.join(timeout=2)
        self.endpoints.close()
        for route in self.snapshot():
            self.remove(route)
        self.deadlines.close()


def _file_keys(p: TopicSpec | ServiceSpec) -> Keys:
    """An entry's keys from its cipher in the file (a session's entries come with its keys)."""
    assert p.cipher is not None, "an entry of a session needs the session's keys"
    return StaticKeys(p.cipher)


def _checked(decode: Callable[[bytes], Any],
             check: Callable[[bytes], None]) -> Callable[[bytes], Any]:
    """``decode``, then ``check`` what it returned (raw CDR no cipher authenticated)."""
    def checked(data: bytes) -> Any:
        value = decode(data)
        check(value)
        return value
    return checked
