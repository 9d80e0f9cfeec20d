"""Admission: who a bridge takes frames and connections from (:class:`Sources`), how many
connections it holds (:class:`ConnectionLimits`), and the loop that accepts them within those
(:class:`Acceptor`). What a connection may do before it is trusted is the link's
(:class:`~rosgate.streamlink.link.Untrusted`).
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .drops import Drop, Reason
from .transport import Address, StreamConnection, StreamListener
from .warn import BUGS
from .wire import envelope

log = logging.getLogger("rosgate")

ACCEPT_POLL = 0.2  # seconds an accept waits before checking whether the acceptor is closing
ACCEPT_BACKOFF = (0.1, 1.0)  # seconds between failed accepts: the first, doubling up to the second


class Sources:
    """Who a link takes frames or connections from: hosts as they appear in a source address,
    and IP networks (``10.0.0.0/24``)."""

    def __init__(self, hosts: Iterable[str], networks: Iterable[str] = ()):
        self.hosts = set(hosts)
        self._seen: dict[str, bool] = {}
        self.networks = []
        for text in networks:
            try:
                self.networks.append(ipaddress.ip_network(text, strict=False))
            except ValueError:
                self.hosts.add(text)  # not an IP network: a host as written (a device address)

    def vouches_for(self, source: Address) -> bool:
        """Whether a link may send to ``source`` unasked (a packetizer's acknowledgement): a
        source it takes frames from for who it is, not one it reads on probation."""
        return self.admits(source)

    def admits(self, source: Address, datagram: bytes | memoryview = b"") -> bool:
        host = source[0]
        if host in self.hosts:
            return True
        if host.startswith("::ffff:"):  # an IPv4 peer on a dual-stack socket
            host = host[7:]
            if host in self.hosts:
                return True
        if not self.networks:
            return False
        known = self._seen.get(host)
        if known is None:  # parsed once per host: a datagram path's cost stays a dict lookup
            try:
                address = ipaddress.ip_address(host.partition("%")[0])
                known = any(address in network for network in self.networks)
            except ValueError:
                known = False
            if len(self._seen) >= 4096:  # hosts come from the network: bounded
                self._seen.clear()
            self._seen[host] = known
        return known

    def __repr__(self) -> str:
        return ", ".join([*sorted(self.hosts), *map(str, self.networks)]) or "nobody"


class KnownSources(Sources):
    """Sources learnt while running: a server's clients, at the addresses their genuine hellos
    or frames came from. A datagram from anywhere else is taken when it is a hello (which the
    server then checks), or on probation, at most ``strangers`` a second from all unknown
    addresses together: a client that moved (a roam, a NAT that picked another port) is heard
    at once, its first frame that opens under its session's key moving its address; the rest is
    ``not_allowed``, before any reassembly."""

    def __init__(self, strangers: float = 0.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(())
        self._known: Counter[Address] = Counter()
        self._lock = threading.Lock()
        self.strangers = strangers
        self.clock = clock
        self._tokens, self._filled = strangers, clock()

    def knows(self, source: Address) -> bool:
        return source in self._known

    def vouches_for(self, source: Address) -> bool:
        return self.knows(source)

    def _on_probation(self) -> bool:
        """One more datagram from an unknown address, within the rate (a token bucket of one
        second's worth); called from the links' receiving threads."""
        with self._lock:
            now = self.clock()
            self._tokens = min(self.strangers,
                               self._tokens + (now - self._filled) * self.strangers)
            self._filled = now
            if self._tokens < 1:
                return False
            self._tokens -= 1
            return True

    def learn(self, source: Address) -> None:
        with self._lock:
            self._known[source] += 1

    def forget(self, source: Address) -> None:
        with self._lock:
            self._known[source] -= 1
            if self._known[source] <= 0:
                del self._known[source]

    def admits(self, source: Address, datagram: bytes | memoryview = b"") -> bool:
        return source in self._known or envelope.is_hello(datagram) or (
            self.strangers > 0 and self._on_probation())

    def __repr__(self) -> str:
        return f"{len(self._known)} client address(es)"


class RecentHosts:
    """Addresses that recently held an authenticated session (a server's clients): they keep
    places of their own in every :class:`ConnectionLimits`, so a robot that was connected gets
    back in while strangers hold every other place. Bounded: the least recently seen is
    forgotten first. With a ``path`` (in the bridge's state folder) they are kept across
    restarts: a restarted server knows its robots. The file is replaced whole (written aside,
    then renamed), mode 0600; one that cannot be read is said once and started afresh."""

    KEEP = 1024  # addresses
    FOR = 24 * 3600.0  # seconds an address counts as recent after its last session began
    MAX_FILE = 256 * 1024  # bytes: a longer file is not ours

    def __init__(self, path: Path | None = None, clock: Callable[[], float] = time.time):
        self.path = path
        self.clock = clock  # wall-clock time: it must mean the same after a restart
        self._seen: dict[str, float] = {}
        self._lock = threading.Lock()
        self._writing = threading.Lock()
        if path is not None:
            self._seen = self._load(path)

    def remember(self, host: str) -> None:
        with self._lock:
            self._seen.pop(host, None)
            self._seen[host] = self.clock()
            while len(self._seen) > self.KEEP:
                del self._seen[next(iter(self._seen))]
            kept = dict(self._seen)
        if self.path is not None:
            self._save(self.path, kept)

    def __contains__(self, host: object) -> bool:
        seen = self._seen.get(host) if isinstance(host, str) else None
        return seen is not None and 0 <= self.clock() - seen < self.FOR

    def _load(self, path: Path) -> dict[str, float]:
        try:
            with path.open("rb") as file:
                data = json.loads(file.read(self.MAX_FILE + 1) or b"{}")
            hosts = data["hosts"]
            now = self.clock()
            seen = {str(h): float(t) for h, t in hosts.items()
                    if isinstance(h, str) and len(h) <= 100 and 0 <= now - float(t) < self.FOR}
        except FileNotFoundError:
            return {}
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
            log.warning("%s: cannot read the recent clients kept there (%s); starting without "
                        "them", path, exc)
            return {}
        return dict(sorted(seen.items(), key=lambda item: item[1])[-self.KEEP:])

    def _save(self, path: Path, seen: dict[str, float]) -> None:
        text = json.dumps({"version": 1, "hosts": seen}, separators=(",", ":")).encode()
        with self._writing:
            aside = path.with_name(f".{path.name}.{os.getpid()}")
            try:
                descriptor = os.open(aside, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW,
                                     0o600)
                with os.fdopen(descriptor, "wb") as file:
                    file.write(text)
                os.replace(aside, path)
            except OSError as exc:
                log.warning("%s: cannot keep the recent clients there (%s): after a restart "
                            "they are strangers until they connect again", path, exc)
                with contextlib.suppress(OSError):
                    aside.unlink()


@dataclass(eq=False)
class Place:
    """A connection's place in :class:`ConnectionLimits`: until :meth:`prove` (its handshake
    proved a listed key) it may be taken back for a newer connection, idle ones first."""

    host: str
    evict: Callable[[], None]  # closes the connection
    spoke: bool = False  # its first handshake message has arrived
    proven: bool = False
    held: bool = True  # False once released or evicted: its release is then nothing

    def heard(self) -> None:
        self.spoke = True

    def prove(self) -> None:
        self.proven = True


class ConnectionLimits:
    """How many connections a bridge holds at once (``bridge.limits``), or handshakes a server
    works on (each costs a Diffie-Hellman): in total, and from one source address. A quarter of
    the total is kept for :class:`RecentHosts`, so strangers from many addresses cannot fill it.
    A handshake takes its place once its first message has arrived, not at accept: a connection
    that only holds a place costs a thread and a descriptor, never a Diffie-Hellman.

    When every place a new connection may have is held, the oldest connection that has not
    proven itself gives its place up (:meth:`take`): an idle one first, then one in its
    handshake. A stranger takes a place back from strangers only; a recent host from anyone
    unproven. So idle connections, from however many addresses, never keep a robot out."""

    def __init__(self, total: int, per_source: int, recent: RecentHosts | None = None):
        self.total = total
        self.per_source = per_source
        self.recent = recent if recent is not None else RecentHosts()
        # places kept for recent hosts: a quarter, at least one when there are two or more
        self.open_to_all = total - (total // 4 if total >= 4 else min(1, total - 1))
        self._by_source: Counter[str] = Counter()
        self.held = 0
        self._places: dict[Place, None] = {}  # taken with take(), oldest first
        self._lock = threading.Lock()

    def admit(self, host: str) -> Drop | None:
        """Take a place for ``host``; None when taken, else why not."""
        with self._lock:
            refused = self._refusal(host)
            if refused is None:
                self._hold(host)
            return refused

    def take(self, host: str, evict: Callable[[], None]) -> Place | Drop:
        """A place for a new connection from ``host`` (``evict`` closes it, should its place be
        taken back), the place of an unproven older one if need be; else why not."""
        with self._lock:
            refused = self._refusal(host)
            victim = self._victim(host) if refused is Drop.TOO_MANY_CONNECTIONS else None
            if refused is not None and victim is None:
                return refused
            if victim is not None:
                self._free(victim)
            place = Place(host, evict)
            self._hold(host)
            self._places[place] = None
        if victim is not None:
            victim.evict()
        return place

    def release(self, host: str) -> None:
        with self._lock:
            self._unhold(host)

    def give_back(self, place: Place) -> None:
        """The place of a connection that closed (nothing when it was taken back already)."""
        with self._lock:
            if place.held:
                self._free(place)

    def _refusal(self, host: str) -> Drop | None:
        if self.held >= self.total or (self.held >= self.open_to_all and host not in self.recent):
            return Drop.TOO_MANY_CONNECTIONS
        if self._by_source[host] >= self.per_source:
            return Drop.TOO_MANY_PER_SOURCE
        return None

    def _victim(self, host: str) -> Place | None:
        """The place to take back for ``host``: the oldest unproven idle one, else the oldest
        unproven; a stranger's only from strangers. None when the source is full itself."""
        if self._by_source[host] >= self.per_source:
            return None
        stranger = host not in self.recent
        unproven = [p for p in self._places if not p.proven
                    and not (stranger and p.host in self.recent)]
        return next((p for p in unproven if not p.spoke), unproven[0] if unproven else None)

    def _hold(self, host: str) -> None:
        self.held += 1
        self._by_source[host] += 1

    def _unhold(self, host: str) -> None:
        self.held -= 1
        self._by_source[host] -= 1
        if not self._by_source[host]:
            del self._by_source[host]

    def _free(self, place: Place) -> None:
        place.held = False
        self._places.pop(place, None)
        self._unhold(place.host)


class _Counted:
    """An accepted connection that gives its place back to the limits when it is closed."""

    def __init__(self, connection: StreamConnection, limits: ConnectionLimits):
        self._connection = connection
        self.send, self.receive = connection.send, connection.receive  # no call in between
        self._limits = limits
        self.place: Place | None = None  # set by the acceptor once it has one
        self._lock = threading.Lock()

    def close(self) -> None:
        try:
            self._connection.close()
        finally:
            with self._lock:
                place, self.place = self.place, None
            if place is not None:
                self._limits.give_back(place)

    def __getattr__(self, name: str) -> Any:  # what else the transport's connection offers
        return getattr(self._connection, name)


def heard(connection: object) -> None:
    """An accepted connection's first handshake message has arrived: taken back after every
    idle one."""
    place = connection.place if isinstance(connection, _Counted) else None
    if place is not None:
        place.heard()


def proven(connection: object) -> None:
    """An accepted connection proved a listed key: its place is never taken back."""
    place = connection.place if isinstance(connection, _Counted) else None
    if place is not None:
        place.prove()


@dataclass(eq=False)
class Acceptor:
    """Accepts connections on a listener until closed, and hands each to ``on_connection``.

    A connection from a source ``sources`` does not admit, or past ``limits``, is closed at once
    and reported to ``on_refused(acceptor, reason, detail)`` (``not_allowed``,
    ``too_many_connections``, ``too_many_per_source``); so is an unproven one whose place is
    taken back for a newer one (``too_many_connections``). When accepting fails (out of file
    descriptors: EMFILE, ENFILE) the loop waits, from 0.1 s doubling to 1 s, and reports
    ``accept_failed``: a listener whose backlog cannot be taken never spins.
    """

    listener: StreamListener
    name: str
    on_connection: Callable[[StreamConnection, Address], None]
    limits: ConnectionLimits
    sources: Sources | None
    on_refused: Callable[[Acceptor, Reason, str], None]

    def __post_init__(self) -> None:
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"accept-{self.name}", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        failures = 0
        while not self.closed.is_set():
            try:
                got = self.listener.accept(ACCEPT_POLL)
            except OSError as exc:
                if self.closed.is_set():
                    return
                failures += 1
                pause = min(ACCEPT_BACKOFF[0] * 2 ** (failures - 1), ACCEPT_BACKOFF[1])
                self.on_refused(self, Drop.ACCEPT_FAILED, f"{exc}; trying again in {pause:g} s")
                self.closed.wait(pause)
                continue
            failures = 0
            if got is not None:
                self._take(*got)

    def _take(self, connection: StreamConnection, peer: Address) -> None:
        host = peer[0]
        if self.sources is not None and not self.sources.admits(peer):
            connection.close()
            self.on_refused(self, Drop.NOT_ALLOWED, f"a connection from {host} (taken from: "
                                                    f"{self.sources})")
            return
        limits = self.limits
        counted = _Counted(connection, limits)

        def evict() -> None:  # its place is taken back for a newer connection
            counted.close()
            self.on_refused(self, Drop.TOO_MANY_CONNECTIONS,
                            f"closed an unauthenticated connection from {host} for a newer one "
                            f"({limits.total} held)")

        place = limits.take(host, evict)
        if not isinstance(place, Place):
            connection.close()
            self.on_refused(self, place, f"closed a connection from {host} ({limits.held} "
                                         f"held, at most {limits.total}, {limits.per_source} "
                                         "per source)")
            return
        counted.place = place
        connection = counted
        try:
            self.on_connection(connection, peer)
        except Exception:  # a bug, or no thread to be had: this connection only
            BUGS.bug("accept_handler", f"{self.name}: error while taking a connection from "
                                       f"{host}")
            connection.close()
            self.on_refused(self, Drop.HANDLER_ERROR, f"a connection from {host}")

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        self.listener.close()
        self._thread.join(timeout=2)
