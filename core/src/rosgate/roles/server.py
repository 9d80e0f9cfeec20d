"""The server role: accepts many clients; each client's entries become a :class:`Session` of
routes. A session outlives its main line for ``session_timeout`` seconds, and a client that
comes back with the same entries gets it back: the same ids (derived from its name and the
entry), its waiting frames first (docs/real-links.md).

Authenticated (``bridge.identity`` and ``clients:``): nothing a connection sends is parsed
before its Noise handshake proves a key listed under ``clients:``, which decides the client's
name and policy (:mod:`rosgate.policy`); each entry the policy refuses, or whose type is not
installed here, is left out, said in both logs. :meth:`ServerRole.reload` applies a changed
policy (SIGHUP; docs/security.md).

This module is the server's life and its main lines (hello, welcome, found, bye, pings, a new
policy); who a client is and where is :mod:`.gate`, the routes of its session :mod:`.sessions`.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from ..admission import Acceptor
from ..config import ClientPolicy
from ..discovery import LOOK_EVERY, Offers, watched
from ..drops import Drop
from ..errors import ConfigError, LinkError
from ..links.base import Link
from ..secure import SecureConnection
from ..services import CallerRoute
from ..streamlink.link import StreamLink
from ..transport import Address, StreamConnection
from ..warn import BUGS
from . import Bridge
from .gate import Session
from .mainline import control, read_taken, taken
from .sessions import SessionRole

log = logging.getLogger("rosgate")

WIND_DOWN = 1.0  # seconds a stopping server waits, at most, for what clients sent before its bye
QUIET = 0.05  # seconds without a frame in that end the wait


class ServerRole(SessionRole):
    """The server role: its main port, each client's main line and session."""

    def __init__(self, bridge: Bridge):
        super().__init__(bridge)
        self.acceptor: Acceptor | None = None  # until start() has its main line
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

    def _main_line(self, connection: StreamConnection, peer: Address) -> None:
        session: Session | None = None

        def on_control(frame: bytes, link: Link, source: Address) -> None:
            nonlocal session
            message = self.read_control(frame, link, source)
            if message is None:
                return
            assert isinstance(link, StreamLink)
            kind = message["type"]
            if kind == "hello" and session is None:
                session = self._welcome(message, link, peer)
                if session is not None:
                    link.trust()
                    link.on_frame = self.router.on_frame  # its data, from the next frame on
            elif kind == "found" and session is not None:
                self._found(session, message, link)
            elif kind == "ready" and session is not None and session.schedule is not None:
                session.schedule.seal_with(message.get("key_id"))
            elif kind == "bye" and session is not None and session.main.current is link:
                log.info("client %r left", session.name)
                self._end(session)

        def before_hello(frame: bytes, link: Link, source: Address) -> None:
            self.router.link_drop(link, Drop.BEFORE_HANDSHAKE, f"data from {source}")

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
        self.life.closing(StreamLink(connection, f"main<-{peer[0]}:{peer[1]}", peer,
                                     before_hello, self.router.on_lost, on_close,
                                     untrusted=self.untrusted, on_control=on_control,
                                     budget=self.bridge.budget(self.bridge.plan.main_line)))

    # -- a client's hello and the names its patterns found ------------------------------------
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

