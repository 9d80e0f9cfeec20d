"""The server role: accepts many clients; each client's entries become a :class:`Session` of
routes. A session outlives its main line for ``session_timeout`` seconds, and a client that
comes back with the same entries gets it back: the same ids (derived from its name and the
entry), its waiting frames first (docs/real-links.md).

Authenticated (``bridge.identity`` and ``clients:``): nothing a connection sends is parsed
before its Noise handshake proves a key listed under ``clients:``, which decides the client's
name and policy (:mod:`rosgate.policy`); each entry the policy refuses, or whose type is not
installed here, is left out, said in both logs. :meth:`ServerRole.reload` applies a changed
policy (SIGHUP; docs/security.md).
"""

from __future__ import annotations

import base64
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from ..actions import Goals, client_goals
from ..admission import Acceptor, ConnectionLimits, KnownSources, RecentHosts, heard
from ..announce import not_installed
from ..config import (
    ActionConfig,
    ClientPolicy,
    Direction,
    ServiceConfig,
    TopicConfig,
)
from ..discovery import LOOK_EVERY, Offers, said_patterns, watched
from ..drops import Drop, Reason
from ..errors import ConfigError, LinkError
from ..links import DatagramLink, Link
from ..policy import refusal, shared
from ..routes import Route
from ..runtime import STATE_VARIABLE, private_folder, state_dir
from ..secure import (
    Busy,
    HandshakeError,
    KeySchedule,
    SecureConnection,
    UnknownKey,
    open_hello,
)
from ..services import CallerRoute
from ..spec import ServiceSpec, TopicSpec
from ..streamlink import LinkSlot, StreamLink
from ..transport import Address, StreamConnection, StreamTransport
from ..warn import BUGS
from ..wire import envelope
from ..wire.envelope import topic_id_for
from . import Bridge, Role, session_keys
from .mainline import (
    PROTOCOL,
    client_entries,
    control,
    flipped,
    found_entries,
    is_control,
    read_taken,
    taken,
    where_error,
)

log = logging.getLogger("rosgate")

#: datagrams a second taken on probation from unknown addresses (a client that moved), for all
#: of them together: more are ``not_allowed``, and such a client is heard at its next hello
STRANGERS_PER_SECOND = 500.0
MAX_HANDSHAKES = 32  # handshakes worked on at once (each a Diffie-Hellman); more are refused
HANDSHAKES_PER_SOURCE = 4  # of those, from one address: a few addresses cannot take them all
WIND_DOWN = 1.0  # seconds a stopping server waits, at most, for what clients sent before its bye
QUIET = 0.05  # seconds without a frame in that end the wait

Entry = TopicConfig | ServiceConfig


@dataclass
class Session:
    """One client, as the server sees it, connected or not."""

    id: int
    token: bytes
    name: str
    topics: list[Any]  # the client's topic list, as it sent it
    services: list[Any]  # and its service list
    main: LinkSlot
    entries: list[Entry | None] = field(default_factory=list)  # checked, in the client's words
    #: how many of them the client listed; the rest its patterns found (None: a name gone)
    listed: int = 0
    by_index: dict[int, Route] = field(default_factory=dict)  # entry -> its route
    refused: dict[int, str] = field(default_factory=dict)  # entry -> why (the policy)
    addresses: dict[DatagramLink, Address] = field(default_factory=dict)
    streams: dict[int, LinkSlot] = field(default_factory=dict)  # port -> dedicated connection
    down_since: float | None = None  # monotonic time the main line was lost; None while up
    policy: ClientPolicy | None = None  # authenticated: the client's entry in clients:
    schedule: KeySchedule | None = None
    hellos: envelope.ReplayWindow = field(default_factory=envelope.ReplayWindow)
    actions: list[Any] = field(default_factory=list)  # its action list, as it sent it
    part_of: dict[int, ActionConfig] = field(default_factory=dict)  # entry -> its action
    owned: set[int] = field(default_factory=set)  # action parts limited to the client's goals
    watch: list[str] = field(default_factory=list)  # its receive patterns, in names here
    watch_services: list[str] = field(default_factory=list)  # its service patterns that call
    made_by: dict[int, str] = field(default_factory=dict)  # found entry -> the client's pattern
    watch_actions: list[str] = field(default_factory=list)  # its action patterns that send goals

    @property
    def routes(self) -> list[Route]:
        return [self.by_index[i] for i in sorted(self.by_index)]

    def close(self) -> None:
        for slot in [self.main, *self.streams.values()]:
            slot.close()
        if self.schedule is not None:
            self.schedule.forget()


def kept_recent_hosts(name: str) -> RecentHosts:
    """The addresses of the server's recent clients, kept in its state folder
    (:class:`~rosgate.runtime.NotPrivate` when another user could write there); in memory only,
    said, when no folder can be had."""
    try:
        folder = private_folder(state_dir(), STATE_VARIABLE)
    except OSError as exc:
        log.warning("%s: no state folder (%s): after a restart its clients are strangers until "
                    "they connect again (set %s to a folder of this user's)", name, exc,
                    STATE_VARIABLE)
        return RecentHosts()
    return RecentHosts(folder / f"{name}.recent-hosts.json")


class ServerRole(Role):
    def __init__(self, bridge: Bridge):
        super().__init__(bridge)
        self.sessions: dict[int, Session] = {}
        self._ids = iter(range(1, 2**32))
        self.router.on_hello = self.on_hello
        self.router.on_heard = self.on_heard
        #: datagram ports take frames from where clients' genuine hellos and frames came from
        #: (and, with identities, a few from elsewhere on probation: :meth:`on_heard`)
        self.clients = KnownSources(STRANGERS_PER_SECOND if self.cfg.secure else 0)
        self._by_key = {p.key: p for p in self.cfg.clients.values()}
        if self.cfg.secure:  # its clients' addresses keep their places across a restart
            self.limits.recent = kept_recent_hosts(self.cfg.name)
        self._handshakes = ConnectionLimits(MAX_HANDSHAKES, HANDSHAKES_PER_SOURCE,
                                            self.limits.recent)
        #: every connection that completed a handshake and is not closed, whatever it does
        #: now (waiting to say hello, in a session, a dedicated port): a reload closes those
        #: whose key it no longer lists
        self._keyed: set[SecureConnection] = set()
        self.acceptor: Acceptor | None = None  # until start() has its main line
        #: who sent each goal, per action (its name here): clients use only their own goals
        self.goals: dict[str, Goals] = {}
        #: the names under clients' receive patterns that publishers here have, told to them
        self.offers = Offers(self.cfg, self.router.ros.node, lambda: list(self.sessions.values()),
                             self._offer, time.monotonic)

    def start(self) -> None:
        plan = self.bridge.plan
        assert plan.main_line is not None and plan.main_address is not None
        self.acceptor = self.accept(
            plan.main_line, plan.main_address,
            lambda connection, peer: self.handshake(
                connection, peer, lambda secure: self._main_line(secure, peer)),
            "bridge.server", name=f"main:{plan.main_address[1]}")
        threading.Thread(target=self._ping_loop, name="server-ping", daemon=True).start()
        threading.Thread(target=self._offer_loop, name="server-offers", daemon=True).start()

    def _offer_loop(self) -> None:
        while not self.life.stopping.wait(LOOK_EVERY):
            try:
                self.offers.look()
            except Exception:  # a graph query that failed (shutting down): the next look retries
                log.debug("offers: could not read the graph", exc_info=True)

    def _offer(self, session: Session, offer: dict[str, dict[str, str]]) -> None:
        link = session.main.current
        if link is not None:
            link.send(control({"type": "offer", "names": offer["topics"],
                               "services": offer["services"], "actions": offer["actions"]}),
                      self.control)

    def wind_down(self) -> None:
        """Every connected client hears ``bye`` first, so its reliable topics wait for the next
        server instead of going into a void; what they sent before it is taken in until the
        links are quiet (at most :data:`WIND_DOWN` seconds)."""
        if self.acceptor is not None:  # first: no client may come back while its session ends
            self.acceptor.close()
        with self._lock:
            lines = [s.main.current for s in self.sessions.values() if s.main.current is not None]
        for link in lines:
            link.send(control({"type": "bye"}), self.control)
        deadline = time.monotonic() + WIND_DOWN
        for link in lines:
            link.drain(max(0.0, deadline - time.monotonic()))
        if lines:
            self._until_quiet(deadline)

    def _until_quiet(self, deadline: float) -> None:
        """Wait until no frame has come in for :data:`QUIET` seconds, or ``deadline``."""
        def frames_in() -> int:
            return sum(link.counters.frames_in for link in self.life.links())

        seen = -1
        while seen != (now := frames_in()) and time.monotonic() < deadline:
            seen = now
            time.sleep(QUIET)  # a pause, not an event: silence has no signal

    def stop(self) -> None:
        if self.acceptor is not None:  # first: no client may come back while its session ends
            self.acceptor.close()
        for session in list(self.sessions.values()):
            self._end(session)
        super().stop()

    # -- the handshake: before it, nothing a connection sends is parsed --------------------
    def handshake(self, connection: StreamConnection, peer: Address,
                  then: Callable[[StreamConnection], None]) -> None:
        """Run the Noise handshake of an accepted connection in a thread of its own, then hand
        the secure connection to ``then``."""
        if not self.cfg.secure:
            then(connection)
            return
        host = peer[0]

        def run() -> None:
            slot = False

            def admit() -> bool:  # once the first message is in: an idle connection takes none
                nonlocal slot
                heard(connection)
                slot = self._handshakes.admit(host) is None
                return slot

            try:
                secure = self.respond(connection, host, lambda key: key in self._by_key, admit)
            finally:
                if slot:
                    self._handshakes.release(host)
            if secure is None:
                return
            with self._lock:
                self._keyed = {c for c in self._keyed if not c.closed}
                self._keyed.add(secure)
            then(secure)

        threading.Thread(target=run, name=f"handshake-{peer[0]}", daemon=True).start()

    def handshake_refused(self, exc: HandshakeError, host: str) -> tuple[Reason, str | None]:
        """A handshake refused for being one too many is counted, not said."""
        if isinstance(exc, Busy):
            return Drop.TOO_MANY_HANDSHAKES, None
        if isinstance(exc, UnknownKey):
            shown = base64.b64encode(exc.key).decode()[:8]
            return Drop.UNKNOWN_CLIENT_KEY, (f"refused a connection from {host}: its key "
                                             f"{shown}... is not in clients:")
        return Drop.BAD_HANDSHAKE, f"refused a connection from {host}: {exc}"

    def _main_line(self, connection: StreamConnection, peer: Address) -> None:
        session: Session | None = None

        def on_frame(frame: bytes, link: Link, source: Address) -> None:
            nonlocal session
            if is_control(frame):
                message = self.read_control(frame, link, source)
                if message is None:
                    return
                assert isinstance(link, StreamLink)
                kind = message["type"]
                if kind == "hello" and session is None:
                    session = self._welcome(message, link, peer)
                    if session is not None:
                        link.trust()
                elif kind == "found" and session is not None:
                    self._found(session, message, link)
                elif kind == "ready" and session is not None and session.schedule is not None:
                    session.schedule.seal_with(message.get("key_id"))
                elif kind == "bye" and session is not None and session.main.current is link:
                    log.info("client %r left", session.name)
                    self._end(session)
                return
            if session is None:
                self.router.link_drop(link, Drop.BEFORE_HANDSHAKE, f"data from {source}")
                return
            self.router.on_frame(frame, link, source)

        def on_close(link: StreamLink) -> None:
            self.life.forget(link)
            if session is not None and session.main.current is link and session.id in self.sessions:
                session.down_since = time.monotonic()
                for route in session.routes:  # calls waiting for the client get no answer now
                    if isinstance(route, CallerRoute):
                        route.fail_all(Drop.LINK_DOWN, "the client's main line was lost")
                log.warning("client %r down (%s); keeping its session for %g s", session.name,
                            link.why or "main line closed", self.cfg.session_timeout)

        assert self.bridge.plan.main_line is not None
        self.life.closing(StreamLink(connection, f"main<-{peer[0]}:{peer[1]}", peer, on_frame,
                                     self.router.on_lost, on_close, untrusted=self.untrusted,
                                     budget=self.bridge.budget(self.bridge.plan.main_line)))

    def _policy_of(self, connection: StreamConnection) -> ClientPolicy | None:
        """The policy of a connection's key as the server's file lists it now (None without
        identities); :class:`ConfigError` for a key that is no longer listed."""
        if not isinstance(connection, SecureConnection):
            return None
        policy = self._by_key.get(connection.peer_key)
        if policy is None:
            raise ConfigError("this client's key is no longer in clients:", file="the server",
                              fix="the server's operator lists it again")
        return policy

    # -- sessions ----------------------------------------------------------------------------
    def _welcome(self, hello: dict[str, Any], link: StreamLink, peer: Address) -> Session | None:
        name = str(hello.get("name", "?"))[:100]
        try:
            # the policy as it is now, not as it was when the handshake completed
            policy = self._policy_of(link.connection)
            if policy is not None and name != policy.name:
                raise ConfigError(f"the key of client {policy.name!r} says hello as {name!r}",
                                  file=f"client {policy.name}",
                                  fix="each client uses its own identity and bridge.name")
            session = self._resume(hello, name)
            resumed = session is not None
            if session is None:
                session = self._new_session(hello, name, policy)
            else:
                session.policy = policy or session.policy
                self._set_found(session, hello)
                self._sync(session)
        except (ConfigError, LinkError) as exc:
            self.refusals.say(f"refused {name} {exc}", f"refused client {name!r} from {peer[0]}: "
                              f"{exc}", logging.ERROR)
            link.send(control({"type": "refused", "error": str(exc)}), self.control)
            return None
        except Exception:  # a bug, or ROS refusing what the checks let through
            BUGS.bug(Drop.SESSION_ERROR, f"could not build the session of client {name!r} from "
                                         f"{peer[0]} (a bug: please report it)")
            self.router.link_drop(link, Drop.SESSION_ERROR, f"client {name!r} from {peer[0]}")
            link.send(control({"type": "refused", "error": "the server could not build this "
                               "session (see its log)"}), self.control)
            return None
        for why in session.refused.values():
            self.refusals.say(f"{name} {why}", why, logging.ERROR)
        session.watch = watched(hello)
        session.watch_services = watched(hello, "watch_services")
        session.watch_actions = watched(hello, "watch_actions")
        self.offers.forget(session)  # what it may receive is offered anew
        self.far_entries(session.by_index, hello.get("entries"))
        routes = [session.by_index.get(i) for i in range(len(session.entries))]
        ids, count = [0 if r is None else r.topic_id for r in routes], len(session.topics)
        welcome: dict[str, Any] = {
            "type": "welcome", "name": self.cfg.name, "session": session.id,
            "topic_ids": ids[:count], "service_ids": ids[count:],
            "refused": [{"entry": self._entry_name(session, i), "error": why}
                        for i, why in sorted(session.refused.items())],
            "entries": [None if r is None else self.router.item(r) for r in routes]}
        if session.schedule is not None:  # a fresh secret for this handshake, inside it
            assert isinstance(link.connection, SecureConnection)
            welcome.update(session.schedule.offer(link.connection.handshake_hash))
        # the session's own: a client tells a restarted server's new session by it (ids start
        # at 1 in every server); without identities it also vouches for datagram hellos
        welcome["token"] = session.token.hex()
        if resumed:  # what its last connection carried: the client writes again what we lack
            welcome["taken"] = taken(session.routes)
        link.send(control(welcome), self.control)
        old = session.main.current
        # after the welcome: what waited goes out under known ids, after what the client's last
        # connection did not get
        session.main.attach(link, read_taken(hello.get("taken")) if resumed else None)
        session.down_since = None
        if old is not None and old is not link:
            old.fail("the client connected again")
        if isinstance(link.connection, SecureConnection):  # it keeps places of its own
            self.limits.recent.remember(peer[0])
        log.info("client %r up: connected from %s with %d topic(s) and %d service(s)%s%s", name,
                 peer[0], len(session.topics), len(session.services),
                 f", {len(session.refused)} refused" if session.refused else "",
                 ", its session kept" if resumed else "")
        return session

    def _set_found(self, session: Session, message: dict[str, Any]) -> None:
        """The topics the client's patterns found, after its listed entries."""
        found, part_of = found_entries(message, self.cfg.defaults, f"client {session.name}")
        before = session.entries[session.listed:]
        session.entries[session.listed:] = found
        made_by, session.made_by = session.made_by, said_patterns(message, session.listed)
        for index in [i for i in session.part_of if i >= session.listed]:
            del session.part_of[index]
        session.part_of.update({session.listed + i: a for i, a in part_of.items()})
        for index in list(session.by_index):
            place = index - session.listed
            if index >= session.listed and (place >= len(found) or found[place] != before[place]):
                # gone, or its place taken by another name (a client found fewer, or reused it)
                route = session.by_index.pop(index)
                self.router.remove(route)
                log.info("client %r: %s is no longer found by its pattern %s: its route is "
                         "removed", session.name, route.label, made_by.get(index, "entries"))
        for index in [i for i in session.refused if i >= len(session.entries)]:
            del session.refused[index]

    def _found(self, session: Session, message: dict[str, Any], link: StreamLink) -> None:
        """A client's patterns found names (or saw them go): their routes, judged by the policy
        exactly as listed entries are; the ids (0: refused or gone) answered as ``placed``."""
        try:
            self._set_found(session, message)
            self._sync(session)
        except (ConfigError, LinkError) as exc:
            log.error("client %r: its found names refused: %s", session.name, exc)
            return
        for index, why in sorted(session.refused.items()):
            if index >= session.listed:
                self.refusals.say(f"{session.name} {why}", why, logging.ERROR)
        routes = [session.by_index.get(i) for i in range(len(session.entries))]
        self.far_entries(session.by_index, message.get("entries"))
        link.send(control({
            "type": "placed", "ids": [0 if r is None else r.topic_id for r in routes],
            "refused": [{"entry": self._entry_name(session, i), "error": why}
                        for i, why in sorted(session.refused.items())],
            "entries": [None if r is None else self.router.item(r) for r in routes]}),
            self.control)

    @staticmethod
    def _entry_name(session: Session, index: int) -> str:
        entry = session.entries[index]
        assert entry is not None  # a name gone is neither refused nor routed
        if index >= session.listed:
            action = session.part_of.get(index)
            name = (f"action {action.action}" if action is not None else entry.topic
                    if isinstance(entry, TopicConfig) else entry.service)
            return f"found[{index - session.listed}] ({name})"
        if isinstance(entry, TopicConfig):
            return f"topics[{index}] ({entry.topic})"
        return f"services[{index - len(session.topics)}] ({entry.service})"

    def _resume(self, hello: dict[str, Any], name: str) -> Session | None:
        """The session a returning client left, if it asks for the same topics; another
        session under its name is ended."""
        with self._lock:
            found = next((s for s in self.sessions.values() if s.name == name), None)
        if found is None:
            return None
        if (found.topics == hello.get("topics") and found.services == hello.get("services", [])
                and found.actions == hello.get("actions", [])
                and hello.get("protocol") == PROTOCOL):
            return found
        log.info("client %r came back with other topics: its old session is dropped", name)
        self._end(found)
        return None

    def _new_session(self, hello: dict[str, Any], name: str,
                     policy: ClientPolicy | None) -> Session:
        if hello.get("protocol") != PROTOCOL:
            raise ConfigError(f"protocol {hello.get('protocol')!r} is not {PROTOCOL}",
                              file=f"client {name}", fix="run the same rosgate version on both")
        if len(self.sessions) >= self.cfg.limits.sessions:
            raise ConfigError(f"the server keeps {len(self.sessions)} sessions already, its "
                              "limit", file=f"client {name}",
                              fix="try again later (bridge.limits.sessions on the server)")
        entries, part_of = client_entries(hello, self.cfg.defaults, f"client {name}")
        session = Session(next(self._ids), os.urandom(16), name, hello["topics"],
                          hello.get("services", []),
                          self.bridge.slot(f"main of {name}", resends=True),
                          entries=list(entries), policy=policy,
                          actions=hello.get("actions", []),
                          part_of=part_of,
                          schedule=KeySchedule(self.cfg.rekey) if self.cfg.secure else None)
        session.listed = len(entries)
        self._set_found(session, hello)
        try:
            self._sync(session)
        except BaseException:  # whatever failed, nothing half-built stays behind
            self._drop_routes(session)
            raise
        with self._lock:
            self.sessions[session.id] = session
        return session

    def _sync(self, session: Session) -> None:
        """Routes for the entries the policy allows (made in order: topics, then services),
        none for the others: a newly refused entry's route is torn down, an action's part whose
        rule now says otherwise of ``shared`` made anew."""
        keyless = {name for (kind, name), r in self.bridge.resolver.plugins.registered.items()
                   if kind == "cipher" and not getattr(r.cls, "session_key_size", 0)}
        resolver, error = self.bridge.resolver, where_error(f"client {session.name}")
        topics = len(session.topics)
        for index, entry in enumerate(session.entries):
            if entry is None:  # a found name that went
                session.refused.pop(index, None)
                gone = session.by_index.pop(index, None)
                if gone is not None:
                    self.router.remove(gone)
                continue
            asked = session.part_of.get(index, entry)  # an action's part: the action
            why = refusal(session.policy, asked, keyless) if session.policy is not None else None
            missing = not_installed(asked.type) if why is None else None
            if missing is not None:  # this entry alone: the client's others are served
                why = (f"{asked.remote}: its type {asked.type} is not installed on the "
                       f"server: {missing}")
            if why is not None:
                session.refused[index] = why
                route = session.by_index.pop(index, None)
                if route is not None:
                    self.router.remove(route)
                continue
            session.refused.pop(index, None)
            goals = self._goals(session, index, keyless)
            if index in session.by_index:
                if (index in session.owned) == (goals is not None):
                    continue
                self.router.remove(session.by_index.pop(index))
            if isinstance(entry, TopicConfig):
                p: TopicSpec | ServiceSpec = resolver.topic(flipped(entry), index, "topics", error)
            else:
                p = resolver.service(flipped(entry), index - topics, "services", error)
            session.by_index[index] = self._route(session, p, goals)
            if index in session.made_by:
                log.info("client %r: its pattern %s found %s (%s): bridged", session.name,
                         session.made_by[index], p.name, entry.type)
            if goals is None:
                session.owned.discard(index)
            else:
                session.owned.add(index)

    def _topic_id(self, session: Session, p: TopicSpec | ServiceSpec) -> int:
        """Derived from the client's name and the entry, so a returning client gets the ids it
        had even from a restarted server; the next free one on a collision."""
        used = {r.topic_id for r in self.router.snapshot()} | {r.topic_id for r in session.routes}
        topic_id = topic_id_for(f"{session.name}\0{p.config.direction}\0{p.name}")
        while topic_id in used or topic_id == envelope.CONTROL_TOPIC:
            topic_id = (topic_id + 1) & 0xFFFFFFFF
        return topic_id

    def _goals(self, session: Session, index: int, keyless: set[str]) -> Goals | None:
        """The record of goals of the action an entry is part of, when the client sends goals
        and may use only its own (None: not an action's part, an action it serves, or one its
        rule says is ``shared``)."""
        action = session.part_of.get(index)
        if (action is None or action.direction is not Direction.TRANSMIT
                or session.policy is not None and shared(session.policy, action, keyless)):
            return None
        with self._lock:
            return self.goals.setdefault(action.remote, Goals())

    def _route(self, session: Session, p: TopicSpec | ServiceSpec,
               goals: Goals | None = None) -> Route:
        t, port = p.config, p.config.port
        way = "to" if t.direction is Direction.TRANSMIT else "from"
        link: Link
        destination = self._no_address  # a stream link has one far side
        if not isinstance(p.transport, StreamTransport):
            link = self.datagram_link(p.transport, p.address, owner=session, sources=self.clients)
            destination = partial(session.addresses.get, link)  # where the client said hello
        elif port is None:
            link = session.main
        else:
            self.listen(p.transport, p.address, self._dedicated_frame(port),
                        handshake=self.handshake, untrusted=self.untrusted, owner=session)
            if port not in session.streams:
                session.streams[port] = self.bridge.slot(f"port {port} of {session.name}")
            link = session.streams[port]
        keys = None if session.schedule is None else session_keys(  # None: the file's cipher
            session.schedule, p, p.name, "s2c", "c2s")
        interface = p.msg_type if isinstance(p, TopicSpec) else p.srv_type
        own = None if goals is None else client_goals(goals, session.name, p.name, interface,
                                                      p.codec_cls.raw)
        return self.router.route(p, self._topic_id(session, p), f"{p.name} ({way} {session.name})",
                                 link, destination, keys, goals=own, mirror=True)

    @staticmethod
    def _no_address() -> Address | None:
        return None

    def _dedicated_frame(self, port: int) -> Any:
        """What frames on a dedicated stream port go to: the first says whose it is."""
        def on_frame(frame: bytes, link: Link, source: Address) -> None:
            try:
                header = envelope.unpack(frame)
            except envelope.EnvelopeError:
                header = None
            if header is not None and header.flags & envelope.FLAG_HELLO:
                session = self.sessions.get(header.topic_id)
                slot = session.streams.get(port) if session is not None else None
                if (session is not None and slot is not None and isinstance(link, StreamLink)
                        and self._hello_is_genuine(session, header, frame, link)):
                    old = slot.current
                    link.trust()
                    slot.attach(link)
                    if old is not None and old is not link:
                        old.fail("the client connected again")
                else:
                    self.router.link_drop(link, Drop.BAD_HELLO, f"from {source}")
                return
            self.router.on_frame(frame, link, source)

        return on_frame

    def _hello_is_genuine(self, session: Session, header: envelope.Header, frame: bytes,
                          link: Link) -> bool:
        """A hello sealed in the session (and, on a stream, over a handshake with the
        session's client key), or, without identities, carrying the session's token."""
        if session.schedule is None:
            return frame[envelope.SIZE:] == session.token
        if isinstance(link, StreamLink):
            connection = link.connection
            if (not isinstance(connection, SecureConnection) or session.policy is None
                    or connection.peer_key != session.policy.key):
                return False
        return (open_hello(session.schedule, header, frame)
                and session.hellos.accept(header.epoch, header.seq) is None)

    def on_hello(self, header: envelope.Header, frame: bytes, link: Link, source: Address) -> None:
        """A datagram hello: the client's address on this link, learnt only from a genuine one."""
        session = self.sessions.get(header.topic_id)
        if session is None or not self._hello_is_genuine(session, header, frame, link):
            self.router.link_drop(link, Drop.BAD_HELLO, f"from {source}")
            return
        if isinstance(link, DatagramLink):  # (hellos of several links share one sequence)
            self._found_at(session, link, source)

    def on_heard(self, route: Route, header: envelope.Header, link: Link,
                 source: Address) -> None:
        """A topic's frame opened under its key and new to its replay window, from ``source``:
        when that is not where its client was, the client moved (a roam, a NAT's new port), and
        is answered there from now on. A forged frame does not open, a replayed one is not new:
        neither moves anyone (WireGuard's rule); nor does one overtaken on the way by a newer
        one (sent from where the client was just before). A frame anyone could have made (no
        session keys: ``insecure: true``) moves nobody either: there only hellos do."""
        if self.clients.knows(source) or not isinstance(link, DatagramLink) \
                or not route.keys.authenticates or not _newest(route.taken(), header):
            return
        with self._lock:
            session = next((s for s in self.sessions.values()
                            if any(r is route for r in s.by_index.values())), None)
        if session is not None:
            self._found_at(session, link, source)

    def _found_at(self, session: Session, link: DatagramLink, source: Address) -> None:
        """Where ``session``'s client is on ``link``, from a genuine hello or frame."""
        with self._lock:
            old = session.addresses.get(link)
            if old == source or session.id not in self.sessions:
                return
            if old is not None:
                self.clients.forget(old)
            self.clients.learn(source)
            session.addresses[link] = source
        if old is not None:  # what waits for an acknowledgement from there goes here now
            link.moved(old, source)
        self.router.resync(session.routes)  # its latched topics, now that it hears us
        if old is None:
            log.debug("client %r is at %s on %s", session.name, source, link.name)
        else:
            log.info("client %r moved from %s to %s on %s", session.name, f"{old[0]}:{old[1]}",
                     f"{source[0]}:{source[1]}", link.name)

    def _end(self, session: Session) -> None:
        with self._lock:
            if self.sessions.pop(session.id, None) is None:
                return
        self._drop_routes(session)

    def _drop_routes(self, session: Session) -> None:
        if not self.life.stopping.is_set():  # at shutdown the engine logs every route itself
            self.router.log_stats(session.routes)  # what this client's topics carried, at the end
        for route in session.routes:
            self.router.remove(route)
        session.by_index.clear()
        session.close()
        for address in session.addresses.values():
            self.clients.forget(address)
        session.addresses.clear()
        self.release(session)  # its ports, unless another session uses them

    # -- a new policy (SIGHUP) ---------------------------------------------------------------
    def reload(self, clients: dict[str, ClientPolicy]) -> None:
        """Apply a new ``clients:``: a client no longer listed (or with another key) is
        disconnected; one whose entries it judges otherwise has them torn down or added and its
        main line recycled, so it hears which now run; the others go on untouched."""
        self.cfg.clients = clients
        self._by_key = {p.key: p for p in clients.values()}
        with self._lock:
            revoked = [c for c in self._keyed if not c.closed and c.peer_key not in self._by_key]
        for connection in revoked:  # handshaken and waiting, or a dedicated port: closed now
            connection.close()
        if revoked:
            log.warning("closed %d connection(s) whose key is no longer in clients:",
                        len(revoked))
        for session in list(self.sessions.values()):
            policy = clients.get(session.name)
            link = session.main.current
            why = "the server's policy changed"
            if policy is None or session.policy is None or policy.key != session.policy.key:
                log.warning("client %r: no longer accepted with its key; its session ends",
                            session.name)
                self._end(session)
                why = "the server's policy no longer accepts this client"
            else:
                before = (dict(session.refused), set(session.by_index))
                session.policy = policy
                try:
                    self._sync(session)
                except (ConfigError, LinkError) as exc:
                    log.error("client %r: cannot apply the new policy (%s); its session ends",
                              session.name, exc)
                    self._end(session)
                else:
                    if (dict(session.refused), set(session.by_index)) == before:
                        continue
                    for refused in session.refused.values():
                        self.refusals.say(f"{session.name} {refused}", refused, logging.ERROR)
                    log.info("client %r: the new policy changed its entries; reconnecting it",
                             session.name)
            if link is not None:
                link.fail(why)
        log.info("applied the policy of %d client(s)", len(clients))

    def _ping_loop(self) -> None:
        """Heartbeat to every connected client; one gone for ``session_timeout`` is dropped."""
        cfg = self.cfg
        while not self.life.stopping.wait(cfg.heartbeat):
            now = time.monotonic()
            for session in list(self.sessions.values()):
                if session.down_since is None:
                    self.heartbeat(session.main.current)
                elif now - session.down_since > cfg.session_timeout:
                    log.warning("client %r gone for %g s: its session is dropped",
                                session.name, cfg.session_timeout)
                    self._end(session)


def _newest(taken: dict[int, int], header: envelope.Header) -> bool:
    """Whether a frame just taken is the newest of its epoch (not a late one)."""
    return taken.get(header.epoch) == header.seq
