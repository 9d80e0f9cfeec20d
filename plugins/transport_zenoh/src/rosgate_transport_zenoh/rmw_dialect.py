"""Entries wired as a ROS 2 node running rmw_zenoh wires its publishers and subscribers
(:mod:`.rmw`), so that rmw_zenoh nodes see rosgate's topics in their graph and exchange data
with them: the zenoh transport's :class:`rosgate_fleet.Dialect` for ``speak: rmw_zenoh``.

It takes the topics that carry bare CDR (``framing: none``, ``codec: cdr``, ``cipher: none``)
and the services with ``codec: cdr`` and ``cipher: none`` (their ``remote:`` is the service's
name on the rmw_zenoh side); ``rosgate check`` marks them ``(rmw_zenoh)``.

* The entry's key is the ROS name the rmw_zenoh side knows the topic by (its ``remote``, or its
  name), and its data goes on ``<domain>/<name>/<type>/<hash>`` with the type's RIHS01 hash;
  the domain is the plugin's ``domain`` option, by default this bridge's own ROS domain.
* Each bus link is one node in rmw_zenoh's graph (``NN``, named as the bridge's ROS node, in
  namespace ``/`` and enclave ``/``); each entry one entity of it: ``MP`` for a topic sent out,
  ``MS`` for one received, with its type, hash and QoS. Tokens are declared before any data.
* Every sample sent carries rmw_zenoh's attachment (sequence number from 1, source timestamp,
  the entity's GID); a sample received without a readable one is dropped
  (``bad_attachment``), as rmw_zenoh drops it.
* A service served here is a complete queryable on its key (``SS``): each query's payload is the
  request's CDR, its attachment says which call it is, and the answer (the response's CDR) goes
  back with the call's sequence number, a timestamp and the caller's GID, as rmw_zenoh's
  servers answer. A service called from here (``SC``) is one query per call with an attachment
  of its own (sequence numbers from 1, this client's GID). A query without a readable
  attachment is not answered and is counted (``bad_attachment``).
* transient_local: the last ``depth`` samples sent are kept for late joiners, and a received
  transient_local topic asks publishers for theirs, with zenoh-ext's advanced publisher and
  subscriber, as rmw_zenoh does.
* The other nodes' tokens are read (:class:`Graph`): each node and entity is logged as it comes
  and goes (with the package to install when its type is not installed here), and counted.
* A peer's receiving topic pattern (``topic: /robot1/**``) takes each publisher those tokens
  announce under it, with the type the token gives (:meth:`RmwZenoh.publishers`).
"""

from __future__ import annotations

import itertools
import logging
import re
import time
from collections import Counter
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import zenoh
import zenoh.ext
from rosgate_fleet import BusLink, BusOutlet

from rosgate import (
    CallerRoute,
    ConfigError,
    Direction,
    ServerRoute,
    ServiceConfig,
    ServiceSpec,
    TopicConfig,
    TopicSpec,
    TypeNotFound,
    declare,
    qos_profile,
    resolve_type,
    topic_id_for,
    type_hash,
)

from . import rmw
from .dialect import KEEP_ALL_HISTORY, MissingTypes, RawAnswers, RawCalls, speaks
from .session import (
    PRIORITIES,
    Declared,
    ZenohPublisher,
    ZenohQuery,
    ZenohSession,
    direct,
    zenoh_message,
)

if TYPE_CHECKING:
    from rosgate_fleet import BusWiring

log = logging.getLogger("rosgate")

NAME = "rmw_zenoh"
BAD_ATTACHMENT = declare("bad_attachment", "an rmw_zenoh sample or call without a readable "
                         "attachment (sequence number, timestamp, GID)")
#: what rmw_zenoh's tokens say of a service's QoS: ROS's services profile (reliable, volatile,
#: keep last 10)
SERVICE_QOS = rmw.Qos(durability=2, depth=10)
_ROS_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


def carried(entry: TopicConfig | ServiceConfig) -> bool:
    """Whether an entry is wired as rmw_zenoh wires it: a topic of bare CDR, or a service whose
    calls lose their envelope on the bus."""
    return speaks(entry)


class RmwZenoh:
    """The dialect of rmw_zenoh (module documentation)."""

    def __init__(self) -> None:
        self._nodes: dict[int, _Node] = {}  # per bus link

    def name(self, entry: TopicConfig | ServiceConfig) -> str | None:
        return NAME if carried(entry) else None

    def check(self, entry: TopicConfig | ServiceConfig, key: str) -> None:
        """The key must be a ROS name (rmw_zenoh's graph shows it), and the type must have the
        RIHS01 hash its keys hold."""
        given = "remote" in entry.lines
        if isinstance(entry, ServiceConfig) and not given:
            raise ConfigError("a service rmw_zenoh nodes call or serve needs remote: (its name "
                              "on their side)", key="service",
                              fix=f"add remote: {entry.service} to this entry")
        field = "remote" if given else "topic"
        if not _ROS_NAME.fullmatch(key):
            raise ConfigError(f"{key!r} is not a ROS name, which rmw_zenoh needs", key=field,
                              fix="write it as a ROS name, e.g. remote: /robot1/cmd_vel")
        try:
            found = type_hash(resolve_type(entry.type))
        except TypeNotFound:  # the resolver says what is wrong with the type itself
            return
        if found is None:
            raise ConfigError(f"this ROS gives no type hash for {entry.type}, which rmw_zenoh's "
                              "keys hold", key="type", fix="use ROS 2 Jazzy or later here")

    def wire(self, wiring: BusWiring, link: BusLink, p: TopicSpec | ServiceSpec) -> None:
        assert p.key is not None
        node = self.node(wiring, link)
        if isinstance(p, ServiceSpec):
            self._service(wiring, link, p, node)
            return
        found = type_hash(p.msg_type)
        assert found is not None, "check() refused the entry"
        qos = rmw.Qos.of(qos_profile(p.config.qos))
        transmit = p.config.direction is Direction.TRANSMIT
        entity = rmw.Entity(node.node, str(next(node.ids)),
                            rmw.Kind.PUBLISHER if transmit else rmw.Kind.SUBSCRIBER,
                            "/" + p.key, p.config.type, found, qos)
        key = entity.key()
        history = (KEEP_ALL_HISTORY if qos.keep_all else qos.depth) if qos.transient_local else 0
        session: ZenohSession = link.session  # type: ignore[assignment]
        link.token(entity.token())  # in the graph before any data
        if transmit:
            publisher = Publisher(session.session, key, entity.gid(), reliable=p.delivery.reliable,
                                  priority=p.delivery.priority, history=history)
            wiring.topic_route(p, topic_id_for(key), BusOutlet(link, key, publisher),
                               bare_names=False)
            return
        route = wiring.receiver(p)
        arrived = link.queued(lambda k, frame: route.deliver(frame, len(frame)),
                              lambda k, reason: route.drop(reason))

        def sample(s: zenoh.Sample) -> None:  # zenoh's thread: the link's thread counts drops
            attachment = s.attachment
            try:
                rmw.read_attachment(attachment.to_bytes() if attachment is not None else None)
            except ValueError as exc:
                link.call_later(route.drop, BAD_ATTACHMENT, f"on {key}: {exc}")
                return
            arrived(key, s.payload.to_bytes())

        link.keep(subscribe(session.session, key, sample, history))

    def _service(self, wiring: BusWiring, link: BusLink, p: ServiceSpec, node: _Node) -> None:
        assert p.key is not None
        found = type_hash(p.srv_type)
        assert found is not None, "check() refused the entry"
        serve = p.config.direction is Direction.RECEIVE
        entity = rmw.Entity(node.node, str(next(node.ids)),
                            rmw.Kind.SERVER if serve else rmw.Kind.CLIENT, "/" + p.key,
                            p.config.type, found, SERVICE_QOS)
        key = entity.key()
        session: RmwSession = link.session  # type: ignore[assignment]
        link.token(entity.token())
        if serve:
            route = wiring.service_route(p, topic_id_for(key), None)
            assert isinstance(route, ServerRoute)
            answers = RawAnswers(link, route)
            session.refused[key] = lambda detail: link.call_later(route.drop, BAD_ATTACHMENT,
                                                                  detail)
            link.serve(key, lambda payload, _answerer, source: answers.request(payload, source),
                       p.config.timeout + 1.0)
            return
        session.callers[key] = (entity.gid(), itertools.count(1))
        calls = RawCalls(link, key, p.config.timeout)
        # its calls are bare CDR: no envelope, so no announcement of rosgate's to say
        caller = wiring.service_route(p, topic_id_for(key), calls, announce=False)
        assert isinstance(caller, CallerRoute)
        calls.route = caller

    def publishers(self, wiring: BusWiring, link: BusLink,
                   listener: Callable[[str, str, bool], None]) -> None:
        """The publishers rmw_zenoh nodes announce in this bridge's domain, by their tokens."""
        def changed(found: rmw.Entity, alive: bool) -> None:
            if found.kind is rmw.Kind.PUBLISHER:
                listener(found.name, found.type, alive)
        self.node(wiring, link).graph.listen(changed)

    def node(self, wiring: BusWiring, link: BusLink) -> _Node:
        """This bridge as a node of rmw_zenoh's graph on ``link``, declared on its first entry."""
        found = self._nodes.get(id(link))
        if found is None:
            session: ZenohSession = link.session  # type: ignore[assignment]
            domain = link.transport.options.domain
            if domain is None:
                domain = wiring.domain_id()
            name = re.sub(r"[^A-Za-z0-9_]", "_", f"rosgate_{wiring.config.name}")  # as its ROS node
            found = self._nodes[id(link)] = _Node(rmw.Node(domain, session.zid(), "0", name))
            link.token(found.node.token())
            link.watch(rmw.everything(domain), found.graph.changed)
        return found


class _Node:
    def __init__(self, node: rmw.Node):
        self.node = node
        self.ids = itertools.count(1)  # the node is 0, as rmw_zenoh numbers a context's first
        self.graph = Graph(node.zid)


class Graph:
    """The nodes and entities rmw_zenoh nodes announce, from their liveliness tokens; runs on
    the bus link's thread."""

    def __init__(self, own: str):
        self.own = own
        self.known: dict[str, rmw.Node | rmw.Entity] = {}  # token -> what it announces
        self.counts: Counter[str] = Counter()  # kind words -> how many there are now
        self.missing = MissingTypes()
        self.listeners: list[Callable[[rmw.Entity, bool], None]] = []

    def changed(self, token: str, alive: bool) -> None:
        found = rmw.parse(token)
        if found is None:
            return
        node = found if isinstance(found, rmw.Node) else found.node
        if node.zid == self.own:
            return
        words = "node" if isinstance(found, rmw.Node) else found.kind.words
        what = (f"{node.namespace.rstrip('/')}/{node.name}" if isinstance(found, rmw.Node)
                else f"{words} on {found.name} [{found.type}] of {node.name}")
        if alive:
            if token in self.known:
                return
            self.known[token] = found
            self.counts[words] += 1
            missing = "" if isinstance(found, rmw.Node) else self.missing(found.type)
            log.info("%s %s: %s%s", NAME, node.zid, what, missing)
        elif self.known.pop(token, None) is not None:
            self.counts[words] -= 1
            log.info("%s %s: %s is gone", NAME, node.zid, what)
        else:
            return
        if isinstance(found, rmw.Entity):
            for listener in list(self.listeners):
                listener(found, alive)

    def listen(self, listener: Callable[[rmw.Entity, bool], None]) -> None:
        """``listener(entity, alive)`` for each entity known now and each that comes or goes."""
        self.listeners.append(listener)
        for found in list(self.known.values()):
            if isinstance(found, rmw.Entity):
                listener(found, True)


class Publisher(ZenohPublisher):
    """A topic's publisher on its rmw_zenoh key: every sample with rmw_zenoh's attachment."""

    def __init__(self, session: zenoh.Session, key: str, gid: bytes, *, reliable: bool,
                 priority: int, history: int):
        self.gid = gid
        self.numbers = itertools.count(1)
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        publisher: Any
        if history:  # transient_local: late joiners query the cache, as rmw_zenoh's do
            publisher = zenoh.ext.declare_advanced_publisher(
                session, key, congestion_control=congestion, priority=PRIORITIES[priority - 1],
                cache=zenoh.ext.CacheConfig(max_samples=history), publisher_detection=True)
        else:
            publisher = session.declare_publisher(
                key, congestion_control=congestion, priority=PRIORITIES[priority - 1])
        super().__init__(publisher)

    def put(self, frame: bytes) -> None:
        try:
            self.publisher.put(frame, attachment=rmw.attachment(next(self.numbers),
                                                                time.time_ns(), self.gid))
        except zenoh.ZError as exc:
            raise OSError(zenoh_message(exc)) from None


def subscribe(session: zenoh.Session, key: str, sample: Callable[[zenoh.Sample], None],
              history: int) -> Declared:
    """A subscription to an rmw_zenoh key; ``history``: also ask publishers that keep samples
    for up to that many each (transient_local)."""
    handler = direct(sample)
    if history:
        return Declared(zenoh.ext.declare_advanced_subscriber(
            session, key, handler, history=zenoh.ext.HistoryConfig(
                detect_late_publishers=True, max_samples=history)))
    return Declared(session.declare_subscriber(key, handler))


class RmwSession(ZenohSession):
    """The zenoh session of a bridge that speaks rmw_zenoh: the queryables of its rmw_zenoh
    services are complete (rmw_zenoh's clients ask only those) and answer with rmw_zenoh's
    attachment; the queries of its rmw_zenoh clients carry one. Everything else is as usual."""

    def __init__(self, session: zenoh.Session):
        super().__init__(session)
        #: served keys -> how a query without a readable attachment is counted (its detail)
        self.refused: dict[str, Callable[[str], None]] = {}
        #: called keys -> the client's GID and its calls' numbers
        self.callers: dict[str, tuple[bytes, Iterator[int]]] = {}

    def serve(self, key: str, on_query: Callable[[str, bytes, Any], None]) -> Declared:
        refuse = self.refused.get(key)
        if refuse is None:
            return super().serve(key, on_query)

        def arrived(query: zenoh.Query) -> None:
            attachment = query.attachment
            try:
                call = rmw.read_attachment(attachment.to_bytes() if attachment is not None
                                           else None)
            except ValueError as exc:
                refuse(f"a call on {key}: {exc}")
                query.drop()
                return
            payload = query.payload
            on_query(str(query.key_expr), payload.to_bytes() if payload is not None else b"",
                     _Answer(query, key, call))

        return Declared(self.session.declare_queryable(key, direct(arrived), complete=True))

    def query(self, key: str, payload: bytes, timeout: float,
              on_reply: Callable[[bytes], None], on_done: Callable[[int], None],
              attachment: bytes | None = None) -> None:
        caller = self.callers.get(key)
        if caller is not None:
            gid, numbers = caller
            attachment = rmw.attachment(next(numbers), time.time_ns(), gid)
        super().query(key, payload, timeout, on_reply, on_done, attachment=attachment)


class _Answer(ZenohQuery):
    """A call's answer, with the attachment rmw_zenoh's servers give it: the call's sequence
    number, the time of the answer and the caller's GID."""

    def __init__(self, query: zenoh.Query, key: str, call: rmw.Attachment):
        super().__init__(query, key)
        self.call = call

    def reply(self, payload: bytes) -> None:
        try:
            self.query.reply(self.key, payload, attachment=rmw.attachment(
                self.call.sequence_number, time.time_ns(), self.call.source_gid))
        except zenoh.ZError as exc:
            raise OSError(zenoh_message(exc)) from None
