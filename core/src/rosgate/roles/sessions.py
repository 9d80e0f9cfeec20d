"""A server's sessions: the routes each client's entries make — listed or found by its patterns,
each judged by the server's policy and refused alone when it says no or its type is not
installed here —, with ids derived from the client's name, so a client that comes back (even
to a restarted server) gets the ids it had; and a session's end, which frees what it held.
"""

from __future__ import annotations

import logging
import os
from functools import partial
from typing import Any

from ..actions import Goals, client_goals
from ..announce import not_installed
from ..config import ClientPolicy, Direction, TopicConfig
from ..discovery import said_patterns
from ..drops import Drop
from ..errors import ConfigError
from ..links.base import Link
from ..policy import refusal, shared
from ..routes import Route
from ..secure import KeySchedule
from ..spec import ServiceSpec, TopicSpec
from ..streamlink.link import StreamLink
from ..transport import Address, StreamTransport
from ..wire import envelope
from ..wire.envelope import topic_id_for
from . import Bridge, session_keys
from .gate import ClientGate, Session
from .mainline import PROTOCOL, client_entries, flipped, found_entries, where_error

log = logging.getLogger("rosgate")


class SessionRole(ClientGate):
    """The part of the server role that keeps its clients' sessions and their routes."""

    def __init__(self, bridge: Bridge):
        super().__init__(bridge)
        self._ids = iter(range(1, 2**32))
        #: who sent each goal, per action (its name here): clients use only their own goals
        self.goals: dict[str, Goals] = {}

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

