"""The server role: accepts many clients; each client's topics become a :class:`Session` of
routes.

A session outlives its main line. When the connection is lost (or falls silent for
``peer_timeout``) the session is kept, by the client's name, for ``session_timeout`` seconds:
its datagram routes keep working and frames of reliable topics for the client wait. A client
that says hello again under the same name with the same topics gets the same session back —
same topic ids, its waiting frames first; with other topics, the old session is dropped and a
new one made. Topic ids are derived from the client's name and the topic, so even a restarted
server gives a returning client the ids it had.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from ..config import Direction, topic_from_mapping
from ..errors import ConfigError, LinkError
from ..links import Acceptor, DatagramLink, KnownSources, Link, LinkSlot, StreamLink
from ..resolver import PreparedService, PreparedTopic
from ..routes import Route
from ..transport import Address, StreamConnection
from ..warn import BUGS
from ..wire import envelope
from ..wire.envelope import topic_id_for
from . import Bridge, Role
from .mainline import (PROTOCOL, client_services, control, flipped, is_control, parse_control,
                       where_error)

log = logging.getLogger("rosgate")


@dataclass
class Session:
    """One client, as the server sees it, connected or not."""

    id: int
    token: bytes
    name: str
    topics: list[Any]  # the client's topic list, as it sent it
    services: list[Any]  # and its service list
    main: LinkSlot
    routes: list[Route] = field(default_factory=list)
    addresses: dict[DatagramLink, Address] = field(default_factory=dict)
    streams: dict[int, LinkSlot] = field(default_factory=dict)  # port -> dedicated connection
    down_since: float | None = None  # monotonic time the main line was lost; None while up

    def close(self) -> None:
        for slot in [self.main, *self.streams.values()]:
            slot.close()


class ServerRole(Role):
    def __init__(self, bridge: Bridge):
        super().__init__(bridge)
        self.sessions: dict[int, Session] = {}
        self._ids = iter(range(1, 2**32))
        self.router.on_hello = self.on_hello
        #: datagram ports take frames only from where clients' genuine hellos came from
        self.clients = KnownSources()

    def start(self) -> None:
        plan = self.bridge.plan
        assert plan.main_line is not None and plan.main_address is not None
        try:
            listener = plan.main_line.listen(plan.main_address)
        except LinkError as exc:
            raise self.bridge.link_error(exc, "bridge.server") from None
        self.acceptor = self.life.closing(Acceptor(listener, f"main:{plan.main_address[1]}",
                                                   self._accepted, self.limits,
                                                   on_refused=self.refused))
        threading.Thread(target=self._ping_loop, name="server-ping", daemon=True).start()

    def stop(self) -> None:
        self.acceptor.close()  # first: no client may come back while its session is ended
        for session in list(self.sessions.values()):
            self._end(session)
        super().stop()

    def _accepted(self, connection: StreamConnection, peer: Address) -> None:
        holder: dict[str, Session] = {}

        def on_frame(frame: bytes, link: Link, source: Address) -> None:
            session = holder.get("session")
            if is_control(frame):
                message = parse_control(frame)
                if message is None:
                    self.router.link_drop(link, "bad_control", f"from {source}")
                    return
                assert isinstance(link, StreamLink)
                link.last_heard = time.monotonic()
                if message["type"] == "hello" and session is None:
                    session = self._welcome(message, link, peer)
                    if session is not None:
                        holder["session"] = session
                        link.trust()
                elif (message["type"] == "bye" and session is not None
                      and session.main.current is link):
                    log.info("client %r left", session.name)
                    self._end(session)
                return
            if session is None:
                self.router.link_drop(link, "before_handshake", f"data from {source}")
                return
            self.router.on_frame(frame, link, source)

        def on_close(link: StreamLink) -> None:
            self.life.forget(link)
            session = holder.get("session")
            if session is not None and session.main.current is link and session.id in self.sessions:
                session.down_since = time.monotonic()
                log.warning("client %r down (%s); keeping its session for %g s", session.name,
                            link.why or "main line closed", self.cfg.session_timeout)

        self.life.closing(StreamLink(connection, f"main<-{peer[0]}:{peer[1]}", peer, on_frame,
                                     self.router.on_lost, on_close, untrusted=self.untrusted))

    def _welcome(self, hello: dict[str, Any], link: StreamLink, peer: Address) -> Session | None:
        name = str(hello.get("name", "?"))[:100]
        session = self._resume(hello, name)
        try:
            if session is None:
                session = self._new_session(hello, name)
        except (ConfigError, LinkError) as exc:
            log.error("refused client %r from %s: %s", name, peer[0], exc)
            link.send(control({"type": "refused", "error": str(exc)}), self.control)
            return None
        except Exception:  # a bug, or ROS refusing what the checks let through
            BUGS.bug("session_error", f"could not build the session of client {name!r} from "
                                      f"{peer[0]} (a bug: please report it)")
            self.router.link_drop(link, "session_error", f"client {name!r} from {peer[0]}")
            link.send(control({"type": "refused", "error": "the server could not build this "
                               "session (see its log)"}), self.control)
            return None
        link.send(control({"type": "welcome", "name": self.cfg.name, "session": session.id,
                           "token": session.token.hex(),
                           "topic_ids": [r.topic_id for r in session.routes[:len(session.topics)]],
                           "service_ids": [r.topic_id
                                           for r in session.routes[len(session.topics):]]}),
                  self.control)
        old = session.main.current
        session.main.attach(link)  # after the welcome: what waited goes out under known ids
        session.down_since = None
        if old is not None and old is not link:
            old.fail("the client connected again")
        log.info("client %r up: connected from %s with %d topic(s) and %d service(s)", name,
                 peer[0], len(session.topics), len(session.services))
        return session

    def _resume(self, hello: dict[str, Any], name: str) -> Session | None:
        """The session a returning client left, if it asks for the same topics; another
        session under its name is ended."""
        with self._lock:
            found = next((s for s in self.sessions.values() if s.name == name), None)
        if found is None:
            return None
        if (found.topics == hello.get("topics") and found.services == hello.get("services", [])
                and hello.get("protocol") == PROTOCOL):
            return found
        log.info("client %r came back with other topics: its old session is dropped", name)
        self._end(found)
        return None

    def _new_session(self, hello: dict[str, Any], name: str) -> Session:
        if hello.get("protocol") != PROTOCOL:
            raise ConfigError(f"protocol {hello.get('protocol')!r} is not {PROTOCOL}",
                              file=f"client {name}", fix="run the same rosgate version on both")
        if len(self.sessions) >= self.cfg.limits.sessions:
            raise ConfigError(f"the server keeps {len(self.sessions)} sessions already, its "
                              "limit", file=f"client {name}",
                              fix="try again later (bridge.limits.sessions on the server)")
        prepared = self._prepare_client_topics(hello, name)
        services = self._prepare_client_services(hello, name)
        session = Session(next(self._ids), os.urandom(16), name, hello["topics"],
                          hello.get("services", []), self.bridge.slot(f"main of {name}"))
        try:
            entries: list[PreparedTopic | PreparedService] = [*prepared, *services]
            for p in entries:  # topics first: the welcome splits the ids so
                session.routes.append(self._route(session, p))
        except BaseException:  # whatever failed, nothing half-built stays behind
            self._drop_routes(session)
            raise
        with self._lock:
            self.sessions[session.id] = session
        return session

    def _prepare_client_topics(self, hello: dict[str, Any], name: str) -> list[PreparedTopic]:
        topics = hello.get("topics")
        if not isinstance(topics, list):
            raise ConfigError("hello without a topic list", file=f"client {name}")
        where = f"client {name}"
        error = where_error(where)
        prepared = []
        for i, mapping in enumerate(topics):
            if not isinstance(mapping, dict):
                raise error(f"topics[{i}]", "not a mapping")
            t = topic_from_mapping(mapping, self.cfg.defaults, where, index=i)
            prepared.append(self.bridge.resolver.topic(flipped(t), i, "topics", error))
        return prepared

    def _prepare_client_services(self, hello: dict[str, Any], name: str) -> list[PreparedService]:
        where = f"client {name}"
        return [self.bridge.resolver.service(flipped(s), i, "services", where_error(where))
                for i, s in enumerate(client_services(hello, self.cfg.defaults, where))]

    def _topic_id(self, session: Session, p: PreparedTopic | PreparedService) -> int:
        """Derived from the client's name and the topic or service, so a returning client gets
        the ids it had even from a restarted server; the next free one on a collision."""
        t = p.config
        used = {r.topic_id for r in self.router.snapshot()} | {r.topic_id for r in session.routes}
        topic_id = topic_id_for(f"{session.name}\0{t.direction}\0{p.name}")
        while topic_id in used or topic_id == envelope.CONTROL_TOPIC:
            topic_id = (topic_id + 1) & 0xFFFFFFFF
        return topic_id

    def _route(self, session: Session, p: PreparedTopic | PreparedService) -> Route:
        t = p.config
        topic_id = self._topic_id(session, p)
        way = "to" if t.direction is Direction.TRANSMIT else "from"
        label = f"{p.name} ({way} {session.name})"
        link: Link
        destination = self._no_address
        port = t.port
        if p.transport.stream and port is None:
            link = session.main
        elif p.transport.stream and port is not None:
            self.listen(p.transport, p.address, self._dedicated_frame(port),
                        untrusted=self.untrusted, owner=session)
            link = session.streams[port] = self.bridge.slot(f"port {port} of {session.name}")
        else:
            datagrams = self.datagram_link(p.transport, p.address, owner=session,
                                           sources=self.clients)
            link = datagrams

            def destination() -> Address | None:  # where the client said hello from, last
                return session.addresses.get(datagrams)
        if isinstance(p, PreparedTopic):
            return self.router.topic(p, topic_id, label, link, destination)
        return self.router.service(p, topic_id, label, link, destination)

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
                        and frame[envelope.SIZE:] == session.token):
                    old = slot.current
                    link.trust()
                    slot.attach(link)
                    if old is not None and old is not link:
                        old.fail("the client connected again")
                else:
                    self.router.link_drop(link, "bad_hello", f"from {source}")
                return
            self.router.on_frame(frame, link, source)

        return on_frame

    def on_hello(self, header: envelope.Header, frame: bytes, link: Link, source: Address) -> None:
        session = self.sessions.get(header.topic_id)
        if session is None or frame[envelope.SIZE:] != session.token:
            self.router.link_drop(link, "bad_hello", f"from {source}")
            return
        if isinstance(link, DatagramLink) and session.addresses.get(link) != source:
            old = session.addresses.get(link)
            if old is not None:
                self.clients.forget(old)
            self.clients.learn(source)
            session.addresses[link] = source
            log.debug("client %r is at %s on %s", session.name, source, link.name)

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
        session.close()
        for address in session.addresses.values():
            self.clients.forget(address)
        session.addresses.clear()
        self.release(session)  # its ports, unless another session uses them

    def _ping_loop(self) -> None:
        """Heartbeat to every connected client; liveness: a client silent for ``peer_timeout``
        is declared down (its connection recycled), one gone for ``session_timeout`` is dropped."""
        cfg = self.cfg
        while not self.life.stopping.wait(cfg.heartbeat):
            now = time.monotonic()
            for session in list(self.sessions.values()):
                link = session.main.current
                if session.down_since is not None:
                    if now - session.down_since > cfg.session_timeout:
                        log.warning("client %r gone for %g s: its session is dropped",
                                    session.name, cfg.session_timeout)
                        self._end(session)
                elif link is not None and now - link.last_heard > cfg.peer_timeout:
                    link.fail(f"silent for {now - link.last_heard:.1f} s")
                elif link is not None:
                    link.send(control({"type": "ping"}), self.control)
