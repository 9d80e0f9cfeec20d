"""The server role: accepts many clients; each client's topics become a :class:`Session` of
routes, removed when the client goes.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from . import envelope
from .config import topic_from_mapping
from .errors import ConfigError, LinkError
from .links import Acceptor, DatagramLink, Link, StreamLink
from .mainline import PROTOCOL, client_services, control, flipped, parse_control, where_error
from .roles import Role
from .routes import Route, TransmitRoute
from .transport import Address, StreamConnection, Transport

if TYPE_CHECKING:
    from .engine import Engine, Prepared, PreparedService

log = logging.getLogger("rosgate")


@dataclass
class Session:
    """One connected client, as the server sees it."""

    id: int
    token: bytes
    name: str
    main: StreamLink
    routes: list[Route] = field(default_factory=list)
    addresses: dict[DatagramLink, Address] = field(default_factory=dict)
    streams: dict[int, StreamLink] = field(default_factory=dict)  # port -> dedicated connection


class ServerRole(Role):
    def __init__(self, engine: Engine):
        super().__init__(engine)
        self.sessions: dict[int, Session] = {}
        self._ids = iter(range(1, 2**32))

    def start(self) -> None:
        main = self.engine.transports[self.cfg.main_line]
        try:
            listener = main.listen(self.engine.main_address)
        except LinkError as exc:
            raise self.engine.bind_error(exc, "bridge.server") from None
        self.engine.closing(Acceptor(listener, f"main:{self.engine.main_address[1]}",
                                     self._accepted))
        threading.Thread(target=self._ping_loop, name="server-ping", daemon=True).start()

    def stop(self) -> None:
        for session in list(self.sessions.values()):
            self._end(session)
        super().stop()

    def routes(self) -> list[Route]:
        with self._lock:
            return [r for s in self.sessions.values() for r in s.routes]

    def transmitter(self, topic_id: int) -> Route | None:
        return next((r for r in self.routes()
                     if r.topic_id == topic_id and isinstance(r, TransmitRoute)), None)

    def _accepted(self, connection: StreamConnection, peer: Address) -> None:
        holder: dict[str, Session] = {}

        def on_frame(frame: bytes, link: Link, source: Address) -> None:
            session = holder.get("session")
            if frame[:2] == envelope.MAGIC and len(frame) > 3 and frame[3] & envelope.FLAG_CONTROL:
                message = parse_control(frame)
                if message is None:
                    self.engine.link_drop(link, "bad_control", f"from {source}")
                elif message["type"] == "hello" and session is None:
                    session = self._welcome(message, link, peer)  # type: ignore[arg-type]
                    if session is not None:
                        holder["session"] = session
                return
            if session is None:
                self.engine.link_drop(link, "before_handshake", f"data from {source}")
                return
            self.engine.on_frame(frame, link, source)

        def on_close(link: StreamLink) -> None:
            self.engine.forget(link)
            session = holder.get("session")
            if session is not None and session.main is link:
                log.info("client %r left", session.name)
                self._end(session)

        self.engine.closing(StreamLink(connection, f"main<-{peer[0]}:{peer[1]}", peer, on_frame,
                                       self.engine.on_drop, on_close))

    def _welcome(self, hello: dict[str, Any], link: StreamLink, peer: Address) -> Session | None:
        name = str(hello.get("name", "?"))
        try:
            if hello.get("protocol") != PROTOCOL:
                raise ConfigError(f"protocol {hello.get('protocol')!r} is not {PROTOCOL}",
                                  file=f"client {name}", fix="run the same rosgate version on both")
            session = Session(next(self._ids), os.urandom(16), name, link)
            prepared = self._prepare_client_topics(hello, name)
            services = self._prepare_client_services(hello, name)
            with self._lock:
                self.sessions[session.id] = session
            for p in [*prepared, *services]:
                session.routes.append(self._route(session, p))
        except ConfigError as exc:
            log.error("refused client %r from %s: %s", name, peer[0], exc)
            link.send(control({"type": "refused", "error": str(exc)}), 0)
            if "session" in locals() and session.id in self.sessions:
                self._end(session)
            return None
        except LinkError as exc:
            log.error("refused client %r: %s", name, exc)
            link.send(control({"type": "refused", "error": str(exc)}), 0)
            self._end(session)
            return None
        link.send(control({"type": "welcome", "name": self.cfg.name, "session": session.id,
                           "token": session.token.hex(),
                           "topic_ids": [r.topic_id for r in session.routes[:len(prepared)]],
                           "service_ids": [r.topic_id for r in session.routes[len(prepared):]]}), 0)
        log.info("client %r connected from %s with %d topic(s) and %d service(s)", name, peer[0],
                 len(prepared), len(services))
        return session

    def _prepare_client_topics(self, hello: dict[str, Any], name: str) -> list[Prepared]:
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
            prepared.append(self.engine.prepare_topic(flipped(t), i, "topics", error))
        return prepared

    def _prepare_client_services(self, hello: dict[str, Any], name: str) -> list[PreparedService]:
        where = f"client {name}"
        return [self.engine.prepare_service(flipped(s), i, "services", where_error(where))
                for i, s in enumerate(client_services(hello, self.cfg.defaults, where))]

    def _route(self, session: Session, p: Prepared | PreparedService) -> Route:
        engine = self.engine
        t = p.config
        topic_id = next(self._ids)
        label = f"{p.name} ({'to' if t.direction == 'transmit' else 'from'} {session.name})"
        host, main_port = engine.main_address
        if p.transport.stream:
            if t.port is None:
                link: Link = session.main
            else:
                self._listen(p.transport, (host, t.port))
                link = _SessionStream(session, t.port)
            return engine.make_route(p, topic_id, label, link)
        link = self.datagram_link(p.transport, (host, t.port or main_port))
        return engine.make_route(p, topic_id, label, link,
                                 lambda link=link: session.addresses.get(link))  # type: ignore[misc]

    def _listen(self, transport: Transport, local: Address) -> None:
        """Listen on a dedicated stream port (LinkError goes back to the client that asked)."""
        with self._lock:
            if (transport.name, local) in self.listening:
                return
            listener = transport.listen(local)
            self.listening.add((transport.name, local))
        port = local[1]

        def on_frame(frame: bytes, link: Link, source: Address) -> None:
            # the first frame on a dedicated connection says whose it is
            try:
                header = envelope.unpack(frame)
            except envelope.EnvelopeError:
                header = None
            if header is not None and header.flags & envelope.FLAG_HELLO:
                session = self.sessions.get(header.topic_id)
                if session is not None and frame[envelope.SIZE:] == session.token:
                    session.streams[port] = link  # type: ignore[assignment]
                else:
                    self.engine.link_drop(link, "bad_hello", f"from {source}")
                return
            self.engine.on_frame(frame, link, source)

        self.engine.closing(Acceptor(listener, f"{transport.name}:{port}",
                                     self.accept_into(on_frame, transport, port)))

    def on_hello(self, header: envelope.Header, frame: bytes, link: Link, source: Address) -> None:
        session = self.sessions.get(header.topic_id)
        if session is None or frame[envelope.SIZE:] != session.token:
            self.engine.link_drop(link, "bad_hello", f"from {source}")
            return
        if isinstance(link, DatagramLink) and session.addresses.get(link) != source:
            session.addresses[link] = source
            log.debug("client %r is at %s on %s", session.name, source, link.name)

    def _end(self, session: Session) -> None:
        with self._lock:
            if self.sessions.pop(session.id, None) is None:
                return
        for route in session.routes:
            self.engine.remove_route(route)
        for stream in session.streams.values():
            stream.close()
        session.main.close()

    def _ping_loop(self) -> None:
        while not self.engine.stopping.wait(self.cfg.heartbeat):
            for session in list(self.sessions.values()):
                session.main.send(control({"type": "ping"}), 0)


class _SessionStream(Link):
    """A server route on a dedicated stream port: the client's connection there, once it came."""

    def __init__(self, session: Session, port: int):
        self.session = session
        self.port = port
        self.name = f"port {port} of {session.name}"
        self.closed = threading.Event()

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        link = self.session.streams.get(self.port)
        return link.send(frame, topic_id) if link is not None else False

    def close(self) -> None:
        pass
