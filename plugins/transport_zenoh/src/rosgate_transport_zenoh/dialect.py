"""Entries wired as zenoh-bridge-ros2dds wires its routes (:mod:`.ros2dds`), so that a
zenoh-bridge-ros2dds robot and rosgate meet as equals: the zenoh transport's
:class:`rosgate_fleet.Dialect`.

With ``plugins: {zenoh: {speak: ros2dds}}`` it takes the entries that carry bare CDR, as that
bridge does: topics with ``framing: none`` and ``codec: cdr``, services with ``codec: cdr`` and
``cipher: none``. ``rosgate check`` marks them ``(zenoh-bridge-ros2dds)``.

* every route holds the liveliness token that bridge would declare for it (``MP`` for a topic
  sent out, ``MS`` for one received, ``SS`` for a service served here, ``SC`` for one called
  from here), with the entry's type and QoS, so the other bridge sets up its side before any
  data flows; the session holds the bridge token ``@/<zid>/@ros2_lv``;
* a transient_local topic sent out keeps its last ``depth`` samples for late joiners to query
  (zenoh-ext's publication cache, as that bridge does), and a transient_local topic received
  asks the publishers on its key for theirs when it starts and when they appear;
* an action (``codec: cdr``, ``cipher: none``) is that bridge's ``<key>/_action/`` layout: its
  three services and two topics as above, under ``<key>/_action/send_goal|cancel_goal|
  get_result|feedback|status``, with one token for the action (``AS`` served here, ``AC``
  called from here) on ``<key>`` with the action's type, and none for its parts;
* a service is a queryable whose query is the request's CDR and whose answer is the response's;
  calls from here carry that bridge's request-header attachment. A call the serving side could
  not answer gets no answer (that bridge has no way to say why), so the caller's timeout speaks;
* the other bridges' tokens are read (:class:`Graph`): each one's routes are logged as they
  come and go, fleets (:mod:`.fleet`) learn robots from them, and a peer's receiving topic
  pattern takes the publishers they announce under it (:meth:`Ros2dds.publishers`).

The core's routes do the rest (codec, counters, ROS entities): service calls cross them in an
envelope that this module adds and removes at the bus's edge, with the ``none`` cipher.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import os
from collections.abc import Callable
from typing import TYPE_CHECKING

from rosgate_fleet import BusAnswerer, BusLink, BusOutlet, Handle

from rosgate import (
    FLAG_FAILED,
    FLAG_REPLY,
    FLAG_REQUEST,
    Address,
    CallerRoute,
    Direction,
    Drop,
    EnvelopeHeader,
    Framing,
    Link,
    Route,
    Sender,
    ServerRoute,
    ServiceConfig,
    ServiceSpec,
    TopicConfig,
    TopicSpec,
    TypeNotFound,
    qos_profile,
    resolve_type,
    topic_id_for,
    unpack_envelope,
)

from . import ros2dds
from .ros2dds import Kind, Qos

if TYPE_CHECKING:
    from rosgate_fleet import BusWiring

    from .session import ZenohSession

log = logging.getLogger("rosgate")

NAME = "zenoh-bridge-ros2dds"
KEEP_ALL_HISTORY = 1000  # samples a keep_all transient_local topic keeps for late joiners


def speaks(entry: TopicConfig | ServiceConfig) -> bool:
    """Whether an entry carries bare CDR as zenoh-bridge-ros2dds does: a topic with
    ``framing: none``, a service with no cipher (its calls lose their envelope on the bus),
    and the feedback and status of an action with no cipher (whose parts come framed)."""
    if entry.codec != "cdr" or entry.cipher != "none":
        return False
    return (isinstance(entry, ServiceConfig) or entry.framing is Framing.NONE
            or ros2dds.action_part(entry.topic) is not None)


class Ros2dds:
    """The dialect of zenoh-bridge-ros2dds (module documentation)."""

    def __init__(self) -> None:
        self._started: dict[int, Graph] = {}  # per bus link: the other bridges' routes

    def name(self, entry: TopicConfig | ServiceConfig) -> str | None:
        return NAME if speaks(entry) else None

    def check(self, entry: TopicConfig | ServiceConfig, key: str) -> None:
        """Every entry it names it can carry: bare framing already excludes a cipher."""

    def wire(self, wiring: BusWiring, link: BusLink, p: TopicSpec | ServiceSpec) -> None:
        self.route(wiring, link, p)

    def route(self, wiring: BusWiring, link: BusLink,
              p: TopicSpec | ServiceSpec) -> tuple[Route, Handle | None]:
        """One entry's route (a fleet entry's, filled for one robot, too) and the token it holds
        (None: an action's part other than its ``send_goal``, which holds the action's)."""
        self.graph(link)
        session: ZenohSession = link.session  # type: ignore[assignment]
        zid = session.zid()
        key = p.key
        assert key is not None
        part = ros2dds.action_part(p.name)
        if isinstance(p, ServiceSpec):
            return self._service(wiring, link, p, zid, part)
        if part is not None:  # an action's feedback or status: bare CDR on the key, as topics
            p = dataclasses.replace(p, config=dataclasses.replace(p.config,
                                                                  framing=Framing.NONE))
        qos = Qos.of(qos_profile(p.config.qos))
        history = (KEEP_ALL_HISTORY if qos.keep_all else qos.depth) if qos.transient_local else 0
        route: Route
        if p.config.direction is Direction.TRANSMIT:
            publisher = session.publisher(key, reliable=p.delivery.reliable,
                                          priority=p.delivery.priority, history=history)
            route = wiring.topic_route(p, topic_id_for(key), BusOutlet(link, key, publisher),
                                       bare_names=False)
        else:
            receiver = route = wiring.receiver(p)
            link.keep(session.subscribe(key, link.queued(
                lambda key, frame: wiring.dispatch(receiver, key, frame),
                lambda key, reason: receiver.drop(reason)), history=history))
        if part is not None:  # an action's parts have its token instead
            return route, None
        return route, link.token(self.topic_token(link, p))

    @staticmethod
    def topic_token(link: BusLink, p: TopicSpec) -> str:
        """The token of a topic's route: ``MP`` sent out, ``MS`` received, with its QoS."""
        session: ZenohSession = link.session  # type: ignore[assignment]
        kind = Kind.PUBLISHER if p.config.direction is Direction.TRANSMIT else Kind.SUBSCRIBER
        assert p.key is not None
        return ros2dds.token(session.zid(), kind, p.key, p.config.type,
                             Qos.of(qos_profile(p.config.qos)))

    def _service(self, wiring: BusWiring, link: BusLink, p: ServiceSpec, zid: str,
                 part: str | None) -> tuple[Route, Handle | None]:
        assert p.key is not None
        route: Route
        if p.config.direction is Direction.RECEIVE:
            server = route = wiring.service_route(p, topic_id_for(p.key), None)
            assert isinstance(server, ServerRoute)
            answers = RawAnswers(link, server)
            link.serve(p.key, lambda payload, _answerer, source: answers.request(payload, source),
                       p.config.timeout + 1.0)
            kinds = Kind.SERVER, Kind.ACTION_SERVER
        else:
            calls = RawCalls(link, p.key, p.config.timeout)
            # its calls are bare CDR: no envelope, so no announcement of rosgate's to say
            caller = route = wiring.service_route(p, topic_id_for(p.key), calls,
                                                  announce=False)
            assert isinstance(caller, CallerRoute)
            calls.route = caller
            kinds = Kind.CLIENT, Kind.ACTION_CLIENT
        if part is None:
            return route, link.token(ros2dds.token(zid, kinds[0], p.key, p.config.type))
        if part == "send_goal":  # one token for the action, with its first part
            return route, link.token(ros2dds.token(zid, kinds[1],
                                                   *ros2dds.action_of(p.key, p.config.type)))
        return route, None

    def publishers(self, wiring: BusWiring, link: BusLink,
                   listener: Callable[[str, str, bool], None]) -> None:
        """The publishers other zenoh-bridge-ros2dds bridges announce, by the ROS name their
        key (under this bridge's ``namespace``) stands for."""
        namespace: str = getattr(link.transport, "namespace", "")  # the zenoh transport's

        def changed(found: ros2dds.Announced, alive: bool) -> None:
            if found.kind is not Kind.PUBLISHER:
                return
            name = found.key.removeprefix(f"{namespace}/") if namespace else found.key
            if name != found.key or not namespace:
                listener(f"/{name}", found.type, alive)
        self.graph(link).listen(changed)

    def graph(self, link: BusLink) -> Graph:
        """The other bridges' routes as seen on ``link``, watched from its first entry on."""
        graph = self._started.get(id(link))
        if graph is None:
            session: ZenohSession = link.session  # type: ignore[assignment]
            graph = self._started[id(link)] = Graph(session.zid())
            link.token(ros2dds.bridge_token(session.zid()))
            link.watch(ros2dds.ALL, graph.changed)
        return graph


class MissingTypes:
    """What a log line about another bridge's or node's entity adds when its type is not
    installed here (the package to install: this side could not bridge it); each type is
    looked up once."""

    def __init__(self) -> None:
        self._said: dict[str, str] = {}  # type -> what is added ("": installed here)

    def __call__(self, type_name: str) -> str:
        said = self._said.get(type_name)
        if said is None:
            try:
                resolve_type(type_name)
                said = ""
            except TypeNotFound as exc:
                said = f" (its type is not installed on this side: {exc})"
            self._said[type_name] = said
        return said


class Graph:
    """The routes other zenoh-bridge-ros2dds bridges (and rosgate bridges speaking their
    convention) announce, from their liveliness tokens; runs on the bus link's thread."""

    def __init__(self, own: str):
        self.own = own
        self.routes: dict[str, ros2dds.Announced] = {}  # token key ->
        self.listeners: list[Callable[[ros2dds.Announced, bool], None]] = []
        self.missing = MissingTypes()

    def changed(self, key: str, alive: bool) -> None:
        announced = ros2dds.parse(key)
        if announced is None or announced.zid == self.own:
            return
        if alive:
            if key in self.routes:
                return
            self.routes[key] = announced
            log.info("%s %s: %s on %s [%s]%s", NAME, announced.zid, announced.kind.words,
                     announced.key, announced.type, self.missing(announced.type))
        elif self.routes.pop(key, None) is None:
            return
        else:
            log.info("%s %s: %s on %s is gone", NAME, announced.zid, announced.kind.words,
                     announced.key)
        for listener in list(self.listeners):
            listener(announced, alive)

    def listen(self, listener: Callable[[ros2dds.Announced, bool], None]) -> None:
        """``listener(route, alive)`` for each route known now and each that comes or goes."""
        self.listeners.append(listener)
        for announced in list(self.routes.values()):
            listener(announced, True)


class RawAnswers(BusAnswerer):
    """A served service's calls as that bridge makes them: each query's payload (the request's
    CDR) is handed to the route in an envelope made here, and the route's answer leaves as the
    response's CDR alone."""

    def __init__(self, link: BusLink, route: ServerRoute):
        super().__init__(link)
        self.route = route
        self.name = f"{link.name}:{route.service.service}"
        self.epoch = int.from_bytes(os.urandom(4), "big")
        self.numbers = itertools.count(1)

    def request(self, payload: bytes, source: tuple[str, int]) -> None:
        """The link's thread: one query."""
        route = self.route
        frame = route.seal(FLAG_REQUEST, self.epoch, next(self.numbers), payload)
        route.on_request(unpack_envelope(frame), frame, self, source)

    def body(self, frame: bytes) -> bytes | None:
        header = unpack_envelope(frame)
        if header.flags & FLAG_FAILED:
            return None  # no answer: the route counted why, the caller's timeout speaks
        return self.route.open(frame, header.epoch)


class RawCalls(Link):
    """A called service's calls as that bridge serves them: the route's request envelope is
    opened here and its body (the request's CDR) is the query, with the request-header
    attachment; the answer (the response's CDR) goes back to the route in an envelope."""

    def __init__(self, link: BusLink, key: str, timeout: float):
        self.bus = link
        self.key = key
        self.timeout = timeout + 1.0  # the call's deadline goes first
        self.name = f"{link.name}:{key}"
        self.closed = link.closed
        self.client = int.from_bytes(os.urandom(8), "little")
        self.route: CallerRoute | None = None  # set once the route is made

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        route = self.route
        assert route is not None
        if self.closed.is_set():
            sender.drop(Drop.LINK_DOWN, f"{self.bus.name} is closed")
            return False
        header = unpack_envelope(frame)
        body = route.open(frame, header.epoch)
        if body is None:
            return False
        bus = self.bus

        def answered(payload: bytes) -> None:
            bus.call_later(self._answer, route, header, payload)

        def done(answers: int) -> None:
            if not answers:
                bus.call_later(sender.drop, Drop.NO_SERVER,
                               f"nothing on {bus.name} answered on {self.key} (no bridge serves "
                               "it, or its server did not answer)")

        session: ZenohSession = bus.session  # type: ignore[assignment]
        try:
            session.query(self.key, body, self.timeout, answered, done,
                          attachment=ros2dds.request_header(self.client, header.seq))
        except OSError as exc:
            sender.drop(Drop.SEND_ERROR, f"query on {self.key}: {exc}")
            return False
        return True

    @staticmethod
    def _answer(route: CallerRoute, request: EnvelopeHeader, payload: bytes) -> None:
        frame = route.seal(FLAG_REPLY, request.epoch, request.seq, payload)
        route.on_reply(unpack_envelope(frame), frame)

    def close(self) -> None:
        pass

