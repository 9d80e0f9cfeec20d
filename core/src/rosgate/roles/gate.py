"""Who a server's clients are, and where: the Noise handshake that proves a client's key (so
many at once, a few per address), the policy that key has now, the hellos that prove a session,
and the addresses a client is answered at, learnt from genuine hellos and frames (a client that
roams or whose NAT picked a new port is followed, a forger never). :class:`Session` is what the
server keeps of one client, connected or not.
"""

from __future__ import annotations

import base64
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..admission import ConnectionLimits, KnownSources, RecentHosts, heard
from ..config import ActionConfig, ClientPolicy, ServiceConfig, TopicConfig
from ..drops import Drop, Reason
from ..errors import ConfigError
from ..links.base import Link
from ..links.datagram import DatagramLink
from ..routes import Route
from ..runtime import STATE_VARIABLE, private_folder, state_dir
from ..secure import Busy, HandshakeError, KeySchedule, SecureConnection, UnknownKey, open_hello
from ..streamlink.link import StreamLink
from ..streamlink.slot import LinkSlot
from ..transport import Address, StreamConnection
from ..wire import envelope
from . import Bridge, Role

log = logging.getLogger("rosgate")

#: datagrams a second taken on probation from unknown addresses (a client that moved), for all
#: of them together: more are ``not_allowed``, and such a client is heard at its next hello
STRANGERS_PER_SECOND = 500.0
MAX_HANDSHAKES = 32  # handshakes worked on at once (each a Diffie-Hellman); more are refused
HANDSHAKES_PER_SOURCE = 4  # of those, from one address: a few addresses cannot take them all

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


class ClientGate(Role):
    """The part of the server role that tells who a client is and where it is."""

    def __init__(self, bridge: Bridge):
        super().__init__(bridge)
        self.sessions: dict[int, Session] = {}
        self.router.on_hello = self.on_hello
        self.router.on_heard = self.on_heard
        #: datagram ports take frames from where clients' genuine hellos and frames came from
        #: (and, with identities, a few from elsewhere on probation: :meth:`on_heard`)
        self.clients = KnownSources(STRANGERS_PER_SECOND if self.cfg.secure else 0)
        self.router.known = self.clients.knows  # a frame from elsewhere comes to on_heard
        self._by_key = {p.key: p for p in self.cfg.clients.values()}
        if self.cfg.secure:  # its clients' addresses keep their places across a restart
            self.limits.recent = kept_recent_hosts(self.cfg.name)
        self._handshakes = ConnectionLimits(MAX_HANDSHAKES, HANDSHAKES_PER_SOURCE,
                                            self.limits.recent)
        #: every connection that completed a handshake and is not closed, whatever it does
        #: now (waiting to say hello, in a session, a dedicated port): a reload closes those
        #: whose key it no longer lists
        self._keyed: set[SecureConnection] = set()

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
        """A topic's frame opened under its key and new to its replay window, from ``source``,
        where no client is known to be (the router asks :attr:`clients` first): the client
        moved (a roam, a NAT's new port), and is answered there from now on. A forged frame
        does not open, a replayed one is not new: neither moves anyone (WireGuard's rule); nor
        does one overtaken on the way by a newer one (sent from where the client was just
        before). A frame anyone could have made (no session keys: ``insecure: true``) moves
        nobody either: there only hellos do."""
        if not isinstance(link, DatagramLink) or not route.keys.authenticates \
                or not _newest(route.taken(), header):
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



def _newest(taken: dict[int, int], header: envelope.Header) -> bool:
    """Whether a frame just taken is the newest of its epoch (not a late one)."""
    return taken.get(header.epoch) == header.seq
