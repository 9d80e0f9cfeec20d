"""The client role: connects its main line to the server (the client starts every connection,
so it can sit behind NAT), sends its entries, builds routes from the answer. Stream entries
without a port ride the main line; datagram ones use the server's main port. Routes are built at
the first welcome and outlive the main line: while it is down, reliable messages wait unsealed
in the :class:`~rosgate.holdback.Holdback` (a datagram link's go out too) and go out first once
it is back, sealed under that session's keys. A server that restarted (another session token)
may answer with other ids: the routes are re-keyed, and frames sealed under the old session
that still wait in a stream slot are dropped (``session_reset``), never sent under a wrong id or
key. Authenticated, routes take their keys from the session's :class:`KeySchedule`
(docs/security.md).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from typing import Any

from ..config import Direction, action_to_mapping, service_to_mapping, topic_to_mapping
from ..config.patterns import denied, far_name, matches
from ..discovery import Discovery, Found, made_by
from ..drops import Drop
from ..errors import ConfigError, LinkError, RosgateError
from ..holdback import Holdback
from ..keyring import NoKey
from ..links.base import Link
from ..links.datagram import DatagramLink
from ..resolver.entries import PreparedAction
from ..router import fixed
from ..routes import Route
from ..secure import KeySchedule, SecureConnection, SessionKeys, seal_hello
from ..services import CallerRoute
from ..spec import ServiceSpec, TopicSpec
from ..streamlink.connector import Connector
from ..streamlink.link import StreamLink
from ..streamlink.slot import LinkSlot
from ..transport import Address, StreamTransport
from . import Answer, Bridge, Role, session_keys
from .mainline import (
    HANDSHAKE_TIMEOUT,
    PROTOCOL,
    control,
    hello_datagram,
    read_taken,
    taken,
)

log = logging.getLogger("rosgate")

MAX_OFFERED = 10_000  # names a server may offer for this side's receive patterns


class ClientRole(Role):
    def __init__(self, bridge: Bridge):
        super().__init__(bridge)
        self.main = bridge.slot(f"main->{self.cfg.server}", resends=True)
        self.session: int | None = None
        self.token = b""
        self.server_name: str | None = None
        self.topic_ids: list[int] | None = None  # as the server numbered our entries (0: refused)
        self.routes: dict[int, Route] = {}  # entry index (topics, then services) -> its route
        self.refused: dict[str, str] = {}  # entry -> why, as the server last said
        self.connected = threading.Event()
        self.hello_to: set[tuple[DatagramLink, Address]] = set()  # every server port we use
        self.schedule: KeySchedule | None = None  # the session's keys (authenticated)
        self._hello_seq = itertools.count(1)
        self._dedicated: dict[int, LinkSlot] = {}
        self.answer = Answer()
        #: what reliable topics take while the server is out of reach
        self.hold = Holdback(self.cfg.queue_frames, self.cfg.queue_bytes)
        #: the topics, services and action parts its pattern entries found, after its listed
        #: entries (None: a name gone); an action takes five places, from the first one's
        self.found: list[TopicSpec | ServiceSpec | None] = []
        self._found_actions: dict[int, PreparedAction] = {}
        self._found_lock = threading.RLock()
        plan = bridge.plan
        #: patterns whose names the server finds (receive topics, services called and actions
        #: whose goals are sent here), and the names under them it offered, by the name here
        self._far = {kind: [p for p in plan.patterns if p.section == kind
                            and p.entry.direction is way]
                     for kind, way in (("topics", Direction.RECEIVE),
                                       ("services", Direction.TRANSMIT),
                                       ("actions", Direction.TRANSMIT))}
        self.offered: dict[str, Found] = {}
        self.discovery = Discovery(self.cfg, plan.patterns, self.router.ros.node, self._add_found,
                                   self._drop_found, time.monotonic, self._tell_found)
        self.service_discovery = Discovery(self.cfg, plan.patterns, self.router.ros.node,
                                           self._add_found, self._drop_found, time.monotonic,
                                           self._tell_found, kind="services")
        self.action_discovery = Discovery(self.cfg, plan.patterns, self.router.ros.node,
                                          self._add_found, self._drop_found, time.monotonic,
                                          self._tell_found, kind="actions")
        assert plan.main_line is not None and plan.main_address is not None
        self.connector = Connector(plan.main_line, plan.main_address, self.main,
                                   self.router.on_frame, self.router.on_lost, self.life,
                                   bridge.backoff, self._handshake, self._lost,
                                   secure=self.initiate if self.cfg.secure else None,
                                   budget=bridge.budget(plan.main_line),
                                   on_closing=lambda link: self.hold.fail(),
                                   on_control=self._on_control)

    def start(self) -> None:
        self.connector.start()
        threading.Thread(target=self._ping_loop, name="client-ping", daemon=True).start()
        self.discovery.start()
        self.service_discovery.start()
        self.action_discovery.start()

    def wind_down(self) -> None:
        """What still waits for the server is counted (``link_down``) before the counters are
        logged."""
        self.hold.close()

    def stop(self) -> None:
        self.discovery.stop()
        self.service_discovery.stop()
        self.action_discovery.stop()
        link = self.main.current
        if self.connected.is_set() and link is not None:
            # a clean stop says goodbye, so the server drops our session now instead of keeping
            # it for session_timeout in case we come back
            link.send(control({"type": "bye"}), self.control)
            link.drain(1.0)
        self.connector.close()
        super().stop()
        if self.schedule is not None:
            self.schedule.forget()

    def _on_control(self, frame: bytes, link: Link, source: Address) -> None:
        message = self.read_control(frame, link, source)
        if message is not None and message["type"] in ("welcome", "refused"):
            self.answer.put(message)
        elif message is not None and message["type"] == "bye":  # the server stops
            self.hold.leave()
        elif message is not None and message["type"] == "placed":
            self._placed(message)
        elif message is not None and message["type"] == "offer":
            self._offered({"topics": message.get("names"),
                           "services": message.get("services", {}),
                           "actions": message.get("actions", {})})

    def entries(self) -> list[Any]:
        """The listed entries, then the topics the patterns found (None: a name gone)."""
        with self._found_lock:
            return [*super().entries(), *self.found]

    def _found_message(self) -> dict[str, Any]:
        with self._found_lock:
            found: list[dict[str, Any] | None] = []
            for place, p in enumerate(self.found):
                action = self._found_actions.get(place)
                if action is not None:  # its parts' places follow: the server takes it whole
                    found.append(action_to_mapping(action.config))
                elif not any(0 < place - first < len(a.parts)
                             for first, a in self._found_actions.items()):
                    found.append(None if p is None else topic_to_mapping(p.config)
                                 if isinstance(p, TopicSpec) else service_to_mapping(p.config))
            # by place (an action's parts each): the server's places, once it takes them apart
            patterns = made_by(self.founds(), self.found)
            for first, action in self._found_actions.items():
                by = next((f.pattern.name for f in self.founds() if f.route is action), None)
                patterns[first:first + len(action.parts)] = [by] * len(action.parts)
            return {"found": found, "patterns": patterns,
                    "entries": [None if p is None else self.router.entry_item(p)
                                for p in self.entries()]}

    def founds(self) -> list[Found]:
        """Every name this side's patterns found, here or offered by the server."""
        return [*list(self.discovery.found.values()),
                *list(self.service_discovery.found.values()),
                *list(self.action_discovery.found.values()), *list(self.offered.values())]

    def _add_found(self, found: Found) -> TopicSpec | ServiceSpec | PreparedAction | None:
        """A name a pattern found, for the server (told after the look) to judge as a listed
        entry."""
        try:
            spec = self.bridge.resolver.found(found.pattern, found.name, found.type)
        except ConfigError as exc:
            log.error("%s: %s cannot be bridged: %s", self.cfg.name, found.name, exc)
            return None
        parts = spec.parts if isinstance(spec, PreparedAction) else [spec]
        with self._found_lock:  # in the places of names gone, so the list stays short
            place = self._free_places(len(parts))
            self.found[place:place + len(parts)] = parts
            if isinstance(spec, PreparedAction):
                self._found_actions[place] = spec
        return spec

    def _free_places(self, count: int) -> int:
        """The first of ``count`` places in a row that names gone left (or the end)."""
        run = 0
        for place, p in enumerate(self.found):
            run = run + 1 if p is None and not self._in_action(place) else 0
            if run == count:
                return place - count + 1
        return len(self.found)

    def _in_action(self, place: int) -> bool:
        return any(0 <= place - first < len(a.parts) for first, a in self._found_actions.items())

    def _drop_found(self, found: Found) -> None:
        with self._found_lock:
            if isinstance(found.route, PreparedAction):
                first = next(f for f, a in self._found_actions.items() if a is found.route)
                places = range(first, first + len(found.route.parts))
                del self._found_actions[first]
            else:
                places = range(self.found.index(found.route), self.found.index(found.route) + 1)
            for place in places:
                self.found[place] = None
                route = self.routes.pop(len(super().entries()) + place, None)
                if route is not None:  # now: its place may take another name first
                    self.router.remove(route)

    def _offered(self, offer: dict[str, Any]) -> None:
        """What the server has under this side's patterns whose names it finds (receive topics,
        services called here): a route for each name new here, none for each name no longer
        offered (the server kept it for its grace)."""
        wanted: dict[str, tuple[Any, str]] = {}
        for kind, names in offer.items():
            if not isinstance(names, dict) or len(names) > MAX_OFFERED:
                continue
            listed = self._listed(kind)
            for far, type_name in names.items():
                if not (isinstance(far, str) and isinstance(type_name, str)):
                    continue
                for p in self._far[kind]:
                    local = far_name(p.entry.remote, p.name, far)
                    if (matches(p.entry.remote, far) and not denied(local, p.entry.deny)
                            and not denied(local, self.cfg.deny) and local not in listed
                            and p.entry.type in ("", type_name)):
                        wanted.setdefault(local, (p, type_name))
                        break
        changed = False
        for local in [n for n in self.offered if n not in wanted]:
            self._drop_found(self.offered.pop(local))
            log.info("%s: %s is no longer offered: its route is removed", self.cfg.name, local)
            changed = True
        for local, (p, type_name) in sorted(wanted.items()):
            made = sum(1 for f in self.offered.values() if f.pattern is p)
            if local in self.offered or made >= p.entry.max_routes:
                continue
            found = Found(p, local, type_name)
            found.route = self._add_found(found)
            if found.route is not None:
                self.offered[local] = found
                log.info("%s: %s[%d] %s found %s (%s): bridged", self.cfg.name, p.section,
                         p.index, p.name, local, type_name)
                changed = True
        if changed:
            self._tell_found()

    def _listed(self, kind: str) -> set[str]:
        entries: list[Any] = getattr(self.cfg, kind)
        return {getattr(e, kind[:-1]) for e in entries if not e.pattern}

    def _tell_found(self) -> None:
        link = self.main.current
        if self.connected.is_set() and link is not None:  # else the next hello says it
            link.send(control({"type": "found", **self._found_message()}), self.control)

    def _placed(self, message: dict[str, Any]) -> None:
        """The server's ids for the found names (0: refused, or gone)."""
        try:
            ids = [int(i) for i in message["ids"]]
            if not all(0 <= i < 2**32 for i in ids):
                raise ValueError("an id out of range")
            with self._found_lock:
                self._note_refusals(message.get("refused", []))
                self._apply(ids)
                self.far_entries(self.routes, message.get("entries"))
                behind = len(ids) < len(self.entries())
        except (KeyError, TypeError, ValueError, RosgateError) as exc:
            log.error("%s: cannot use the server's answer: %s", self.cfg.name, exc)
            return
        self._say_hello()  # a found name's datagram link may be new: the server learns it
        self.router.start_announcing([self.routes[i] for i in range(len(ids)) if i in self.routes])
        if behind:  # names found while the server placed the others
            self._tell_found()

    def _handshake(self, link: StreamLink) -> bool:
        """Send our entries; build, re-key or drop their routes from the server's answer."""
        self.hold.handshake()
        self.answer.got.clear()
        plan = self.bridge.plan
        link.send(control({"type": "hello", "protocol": PROTOCOL, "name": self.cfg.name,
                           "topics": [topic_to_mapping(p.config) for p in plan.topics],
                           "services": [service_to_mapping(p.config) for p in plan.services],
                           "actions": [action_to_mapping(a.config) for a in plan.actions],
                           "watch": [p.entry.remote for p in self._far["topics"]],
                           "watch_services": [p.entry.remote for p in self._far["services"]],
                           "watch_actions": [p.entry.remote for p in self._far["actions"]],
                           **self._found_message(),
                           "taken": taken(self.routes.values())}),
                  self.control)
        answer = self.answer.wait(link, self.life.stopping, HANDSHAKE_TIMEOUT)
        if answer is None:
            if link.closed.is_set() and not self.life.stopping.is_set():
                self.connector.failed(LinkError(
                    "the server closed the connection before answering our hello (does it "
                    "require identities? then set bridge.identity and server_key)"))
            elif not self.life.stopping.is_set():
                log.warning("%s: no answer to the handshake from %s", self.cfg.name,
                            self.cfg.server)
            return False
        if answer["type"] == "refused":
            log.error("%s: the server refused us: %s", self.cfg.name, answer.get("error"))
            return False
        try:
            ids = [int(i) for i in answer["topic_ids"] + answer.get("service_ids", [])]
            if not len(super().entries()) <= len(ids) <= len(self.entries()):
                raise ValueError("topic and service id count does not match")
            if not all(0 <= i < 2**32 for i in ids):  # 0: an entry the server refused
                raise ValueError("a topic or service id out of range")
            session, token = int(answer["session"]), bytes.fromhex(answer.get("token", ""))
            self.server_name = str(answer["name"])
            if self.cfg.secure:
                self._install_keys(answer, link)
            with self._found_lock:
                self._note_refusals(answer.get("refused", []))
                self._apply(ids)
                self.far_entries(self.routes, answer.get("entries"))
        except (KeyError, TypeError, ValueError, RosgateError) as exc:
            log.error("%s: cannot use the server's answer: %s", self.cfg.name, exc)
            if self.topic_ids is None:
                self._unbuild()  # half-built: the next handshake starts clean
            return False
        new_session = (session, token) != (self.session, self.token)
        if new_session:  # a restarted server reuses ids
            self.session, self.token = session, token
            for slot in [self.main, *self._dedicated.values()]:
                # what waited there was sealed under the old session's keys
                slot.discard(Drop.SESSION_RESET)
            for slot in self._dedicated.values():  # they must introduce themselves anew
                if slot.current is not None:
                    slot.current.fail("the server started a new session")
        # only a server that kept our session says what it took: then what our last connection
        # carried and it did not get goes again, first
        got = read_taken(answer.get("taken"))
        if got is None:
            self.main.forget_written()
        link.last_heard = time.monotonic()
        self.main.attach(link, got)  # now, not when the connector gets to it: a stop says bye
        self.connected.set()
        self._say_hello()
        # what waited for the server goes first, sealed under this session's keys
        self.hold.resume(new_session)
        self.router.start_announcing(list(self.routes.values()))  # the server hears us now
        self.router.resync(list(self.routes.values()))
        log.info("%s: server %r up at %s", self.cfg.name, self.server_name, self.cfg.server)
        if len(ids) < len(self.entries()):  # names found while the server answered
            self._tell_found()
        return True

    def _install_keys(self, answer: dict[str, Any], link: StreamLink) -> None:
        """The session's secret from the welcome; then say we hold it, so the server seals
        under it too."""
        connection = link.connection
        assert isinstance(connection, SecureConnection)
        rekey = float(answer.get("rekey", self.cfg.rekey))
        if self.schedule is None or self.schedule.rekey != rekey:
            old = self.schedule
            self.schedule = KeySchedule(rekey)
            if old is not None:  # routes follow the schedule they were given: give them this
                for route in self.routes.values():
                    if isinstance(route.keys, SessionKeys):
                        route.keys.schedule = self.schedule
        key_id = self.schedule.accept(answer, connection.handshake_hash)
        link.send(control({"type": "ready", "key_id": key_id}), self.control)

    def _note_refusals(self, refused: list[Any]) -> None:
        now = {str(r["entry"]): str(r["error"]) for r in refused}
        for entry, why in now.items():
            if self.refused.get(entry) != why:
                log.error("%s: the server refused %s: %s", self.cfg.name, entry, why)
        self.refused = now

    def _lost(self, link: StreamLink) -> None:
        self.connected.clear()
        for route in self.routes.values():  # calls waiting for an answer get none now
            if isinstance(route, CallerRoute):
                route.fail_all(Drop.LINK_DOWN, "the session's main line was lost")
        log.warning("%s: server %r down (%s); reconnecting", self.cfg.name, self.server_name,
                    link.why or "main line closed")
        self._say_hello()  # from where we are now: a server that kept our session answers there

    def _apply(self, ids: list[int]) -> None:
        """Make the routes match the server's answer: one per entry it accepted (id > 0),
        renumbered when a restarted server numbered them anew; none for a refused entry."""
        renumbered = self.topic_ids is not None and any(
            old and new and old != new for old, new in zip(self.topic_ids, ids, strict=False))
        if renumbered:
            for slot in [self.main, *self._dedicated.values()]:
                slot.discard(Drop.SESSION_RESET)
        # ids may cover fewer entries: names the patterns found while the server placed these
        for index, (p, topic_id) in enumerate(zip(self.entries(), ids, strict=False)):
            route = self.routes.get(index)
            if topic_id == 0 or p is None:
                if route is not None:
                    self.router.remove(self.routes.pop(index))
            elif route is None:
                self.routes[index] = self._route(p, topic_id)
            elif route.topic_id != topic_id:
                self.router.renumber(route, topic_id)
        self.topic_ids = ids

    def _route(self, p: TopicSpec | ServiceSpec, topic_id: int) -> Route:
        t = p.config
        way = "to" if t.direction is Direction.TRANSMIT else "from"
        label = f"{p.name} ({way} {self.server_name})"
        link: Link
        destination = fixed(p.address)
        if isinstance(p.transport, StreamTransport):
            link = self.main if t.port is None else self._dedicated_stream(p)
        else:  # frames from the server only
            link = self.datagram_link(p.transport, p.local,
                                      sources=self.sources(p.transport, p.address[0]))
            self.hello_to.add((link, p.address))
        # None: the file's cipher; else by the server's name for it (both derive the same keys)
        keys = None if self.schedule is None else session_keys(
            self.schedule, p, p.config.remote, "c2s", "s2c")
        # announcements start once the server has our datagram hello (its ports take frames
        # only from where a hello came from)
        return self.router.route(p, topic_id, label, link, destination, keys, announce=False,
                                 hold=self.hold, mirror=True)

    def _unbuild(self) -> None:
        super().stop()
        self.routes.clear()
        for slot in self._dedicated.values():
            slot.close()  # its connector ends with it
        self._dedicated.clear()
        with self._lock:
            links = list(self.datagram_links.values())
            self.datagram_links.clear()
            self.hello_to.clear()
        for link in links:
            link.close()
            self.life.forget(link)

    def _dedicated_stream(self, p: TopicSpec | ServiceSpec) -> LinkSlot:
        address, port = p.address, p.address[1]
        if port in self._dedicated:
            return self._dedicated[port]
        slot = self.bridge.slot(f"{p.config.transport}->{address[0]}:{port}")

        def introduce(link: StreamLink) -> bool:
            # a session the server kept takes the hello even while the main line is down; a
            # new session makes the handshake recycle this connection
            if self.session is None:
                return False  # wait for the first handshake
            return link.send(self._hello(), self.control)

        Connector(p.transport, address, slot, self.router.on_frame, self.router.on_lost, self.life,
                  self.bridge.backoff, introduce,
                  secure=self.initiate if self.cfg.secure else None,
                  budget=self.bridge.budget(p.transport)).start()
        self._dedicated[port] = slot
        return slot

    def _hello(self) -> bytes:
        assert self.session is not None
        if self.schedule is not None:
            return seal_hello(self.schedule, self.session, next(self._hello_seq))
        return hello_datagram(self.session, self.token)

    def _say_hello(self) -> None:
        if self.session is None:
            return
        for link, to in list(self.hello_to):
            try:
                hello = self._hello()
            except NoKey:  # between two connections: the keys come with the next welcome
                return
            link.send(hello, self.control, to)

    def _ping_loop(self) -> None:
        """Heartbeat on the main line; datagram hellos go on while it is down, so the server
        keeps our address."""
        while not self.life.stopping.wait(self.cfg.heartbeat):
            if self.connected.is_set():
                self.heartbeat(self.main.current)
            self._say_hello()
