"""A peer's topic and service patterns. A transmit topic pattern finds the publishers on this
side's graph (:class:`~rosgate.discovery.Discovery`, as a client's) and makes a route per name,
on the entry's own link (its ``port``: every name it finds shares it, told apart by the
envelope's topic id, derived from the name as a listed entry's). The far peer learns the names
from the link's *roster*: an announcement (``FLAG_ANNOUNCE``) under the id of
:data:`ROSTER_NAME`, sealed like the entry's frames, that lists every name the link carries with
its type and RIHS01 hash, sent when a name appears or goes and every
:data:`~rosgate.announce.ANNOUNCE_EVERY` seconds.

The receiving peer makes a route for an announced name only if one of its own receive patterns
takes it (its ``remote:`` matches, not denied, within ``max_routes``): a peer never publishes a
name its own file does not take. A name left out of the roster (gone past the far side's
``pattern_grace``), or a roster unheard for longer than the far peer may be silent, takes its
route down: the publisher here is destroyed. A name both sent and received here (a publisher on
each side) never echoes back: :mod:`rosgate.echo`.

Service patterns run the other way: a receive pattern finds the servers on its side (their calls
come from the far peer) and makes a serving route per name on its port; its roster goes back
to where the far peer's *asks* come from (an empty roster its transmit service patterns send on
their link, whose port the far side cannot know before). The calling peer makes a proxy for
each announced name its own transmit service patterns take, and removes it when the name goes.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .. import announce
from ..announce import ANNOUNCE_EVERY, ANNOUNCE_FAST, YOUNG
from ..config import Direction
from ..config.kinds import ROS_NAME_MAX
from ..config.patterns import denied, far_name, matches
from ..discovery import Discovery, Found, Refusals
from ..drops import Drop
from ..echo import EchoGuard
from ..errors import CipherError, ConfigError
from ..keyring import Keys, NoKey, StaticKeys
from ..links.base import Link, NoLink
from ..router import fixed
from ..routes import ReceiveRoute, Route, TransmitRoute
from ..services import CallerRoute, ServerRoute
from ..spec import ServiceSpec, TopicSpec
from ..streamlink.connector import Connector
from ..transport import Address, StreamTransport
from ..wire import envelope
from ..wire.control import ControlError, parse
from ..wire.envelope import topic_id_for
from . import Role

if TYPE_CHECKING:
    from ..resolver.plan import Pattern

#: an entry's keys on its link, by a name there (default: its remote; None: its file's cipher)
KeysOf = Callable[[TopicSpec | ServiceSpec, str | None], Keys | None]

log = logging.getLogger("rosgate")

#: the name a link's roster is announced under (a name no ROS node can take: '_rosgate' is the
#: bridges' own namespace)
ROSTER_NAME = "/_rosgate/names"
ROSTER_ID = topic_id_for(ROSTER_NAME)
MAX_NAMES = 1000  # names one roster may carry
MAX_ROSTERS = 16  # links one far peer may announce rosters for
_NAME = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")
#: a type a roster may name, by the kind of names it carries
_TYPES = {kind: re.compile(rf"[A-Za-z_][A-Za-z0-9_]*/{part}/[A-Za-z_][A-Za-z0-9_]*")
          for kind, part in (("topics", "msg"), ("services", "srv"))}
ASK = "ask"  # the kind of a roster that asks for the far side's servers (names none)


@dataclass
class Sending:
    """One link's roster: the names this side's patterns found and carry on it (``kind``
    topics or services), or an ask (none)."""

    route: Route  # seals the roster (its keys, its sequence)
    link: Link
    to: Address | None  # None: a serving link's, until the far side asks
    key: str  # how the far side tells this link's roster from another's
    kind: str
    seq: Iterator[int] = field(default_factory=lambda: itertools.count(1))
    names: dict[str, dict[str, Any]] = field(default_factory=dict)  # far name -> item


@dataclass
class Made:
    """A route a far peer's roster made here: a topic's receiving route, a service's proxy."""

    route: ReceiveRoute | CallerRoute
    pattern: Pattern
    roster: tuple[str, str]  # (kind, key) of the roster that announced it
    local: str  # its name here


class PeerPatterns:
    """The patterns of a peer ``role``: ``keys_of`` keys a route as the role's listed entries;
    ``heard_from`` the routes whose far side is the peer, ``callers`` its proxies of the
    peer's services; ``quiet``: seconds the peer may be silent before the names it announced
    are taken down."""

    def __init__(self, role: Role, keys_of: KeysOf, heard_from: list[Route],
                 callers: list[CallerRoute], quiet: float):
        self.role, self.cfg, self.router = role, role.cfg, role.router
        self.keys_of, self.heard_from, self.callers = keys_of, heard_from, callers
        self.quiet = quiet
        plan, node = role.bridge.plan, role.router.ros.node
        #: a bus's patterns are its role's (it finds what the bus announces), not these
        patterns = [p for p in plan.patterns if p.checked is None or p.checked.key is None]
        self.sending: dict[tuple[str, int], Sending] = {}  # by the finding pattern's place
        self._links: dict[tuple[str, str, Address], Sending] = {}
        #: what takes a far peer's names: receive topic patterns, transmit service patterns
        self.taking = {kind: [p for p in patterns if p.section == kind
                              and p.entry.direction is way]
                       for kind, way in (("topics", Direction.RECEIVE),
                                         ("services", Direction.TRANSMIT))}
        #: what opens the far side's rosters, by kind and cipher; and each roster's replay
        #: window, by the opener, its kind and its link (one sequence per sender's link)
        self.openers: dict[tuple[str, str], Route] = {}
        self._windows: dict[tuple[int, str, str], Route] = {}
        self.discovery = Discovery(self.cfg, patterns, node, self._add, self._drop,
                                   time.monotonic, self._tell)
        self.service_discovery = Discovery(self.cfg, patterns, node, self._add,
                                           self._drop, time.monotonic, self._tell,
                                           kind="services")
        self.made: dict[tuple[str, str], Made] = {}  # (kind, far name) -> its route here
        self.rosters: dict[tuple[str, str], float] = {}  # (kind, key) -> when last heard
        self.sent: dict[str, TransmitRoute] = {}  # local name -> its transmitting route
        self.refusals = Refusals()
        self._lock = threading.RLock()
        self._born = time.monotonic()

    def start(self) -> None:
        for p in self.discovery.patterns:
            self.sending[("topics", p.index)] = self._sending(p, "topics")
        for p in self.service_discovery.patterns:
            self.sending[("services", p.index)] = self._sending(p, "services")
            self._opener(p)  # a serving pattern opens the far side's asks
        for p in self.taking["topics"]:
            self._taking(p)
        for p in self.taking["services"]:
            self._sending(p, ASK)
            self._opener(p)
        if self.openers:
            self.router.on_unknown_announcement = self._heard
        self.discovery.start()
        self.service_discovery.start()
        if self._links or self.openers:
            threading.Thread(target=self._loop, name="peer-patterns", daemon=True).start()

    def stop(self) -> None:
        self.discovery.stop()
        self.service_discovery.stop()

    # -- sending -----------------------------------------------------------------------------
    def _spec(self, p: Pattern) -> TopicSpec | ServiceSpec:
        spec = p.checked  # on a point-to-point link; a service's on a datagram one (resolver)
        assert isinstance(spec, TopicSpec | ServiceSpec)
        return spec

    def _sending(self, p: Pattern, kind: str) -> Sending:
        """The link a pattern's routes share (one per port), and its roster: a transmit topic
        pattern's to the peer, a receive service pattern's where it serves (sent back to
        where asks come from), a transmit service pattern's ask."""
        spec = self._spec(p)
        where = (kind, spec.transport.name, spec.address)
        if where in self._links:
            return self._links[where]
        link: Link
        key, sources = f"{p.section}[{p.index}].port", self.role.sources(spec.transport,
                                                                           self.cfg.peer)
        if isinstance(spec.transport, StreamTransport):
            link = slot = self.role.bridge.slot(f"{spec.transport.name}->{self.cfg.peer}:"
                                                f"{spec.address[1]}")
            Connector(spec.transport, spec.address, slot, self.router.on_frame,
                      self.router.on_lost, self.role.life, self.role.bridge.backoff,
                      budget=self.role.bridge.budget(spec.transport)).start()
        else:
            serves = kind == "services"
            link = self.role.datagram_link(spec.transport, spec.address if serves else
                                           spec.local, key, sources=sources)
        keys = self.keys_of(spec, ROSTER_NAME) or StaticKeys(_cipher(spec))
        route = Route(spec.config, ROSTER_ID, None, keys, self.router.warner,
                      f"names on {link.name}")
        sending = self._links[where] = Sending(
            route, link, None if kind == "services" else spec.address,
            f"{spec.transport.name}:{spec.address[1]}", kind)
        return sending

    def _add(self, found: Found) -> TransmitRoute | ServerRoute | None:
        """A name a pattern found here: said in its link's roster first (so the far side's
        route is there for its first message), then its route."""
        try:
            spec = self.role.bridge.resolver.found(found.pattern, found.name, found.type)
        except ConfigError as exc:
            log.error("%s: %s cannot be bridged: %s", self.cfg.name, found.name, exc)
            return None
        sending = self.sending[(found.pattern.section, found.pattern.index)]
        with self._lock:
            sending.names[spec.config.remote] = self.router.entry_item(spec)
        self._send(sending)
        route = self.router.route(spec, topic_id_for(spec.config.remote), spec.name,
                                  sending.link, fixed(spec.address), self.keys_of(spec, None))
        if isinstance(route, ServerRoute):  # its calls wait for the caller's type
            route.check.expect(route.drop)
            self.heard_from.append(route)
            return route
        assert isinstance(route, TransmitRoute)
        with self._lock:
            self.sent[found.name] = route
            self._pair(found.name)
        return route

    def _drop(self, found: Found) -> None:
        sending = self.sending[(found.pattern.section, found.pattern.index)]
        with self._lock:
            sending.names.pop(found.route.entry.remote, None)
            self.sent.pop(found.name, None)
            if found.route in self.heard_from:
                self.heard_from.remove(found.route)
        self.router.remove(found.route)

    def _tell(self) -> None:
        for sending in list(self._links.values()):
            self._send(sending)

    def _send(self, sending: Sending) -> None:
        if sending.to is None:
            return  # a serving link's, before the far side asked
        with self._lock:
            body = json.dumps({"link": sending.key, "kind": sending.kind,
                               "names": sending.names}, separators=(",", ":")).encode()
        route = sending.route
        try:
            frame = route.seal(envelope.FLAG_ANNOUNCE, route.keys.epoch(),
                               next(sending.seq), body)
        except (NoKey, CipherError):
            return  # before the handshake: the next roster comes soon
        sending.link.send(frame, route.announcer, sending.to)

    # -- receiving ---------------------------------------------------------------------------
    def _taking(self, p: Pattern) -> None:
        """A receive topic pattern's link bound (or listened on), and an opener for its
        cipher."""
        spec = self._spec(p)
        sources = self.role.sources(spec.transport, self.cfg.peer)
        key = f"topics[{p.index}].port"
        if isinstance(spec.transport, StreamTransport):
            self.role.listen(spec.transport, spec.address, self.router.on_frame, key,
                             sources=sources)
        else:
            self.role.datagram_link(spec.transport, spec.address, key, sources=sources)
        self._opener(p)

    def _opener(self, p: Pattern) -> None:
        """What opens the rosters the far side seals with ``p``'s kind and cipher."""
        if (p.section, p.entry.cipher) not in self.openers:
            spec = self._spec(p)
            keys = self.keys_of(spec, ROSTER_NAME) or StaticKeys(_cipher(spec))
            self.openers[(p.section, p.entry.cipher)] = Route(
                spec.config, ROSTER_ID, None, keys, self.router.warner,
                f"names ({p.section}) from {self.cfg.peer}")

    def _heard(self, header: envelope.Header, frame: bytes, link: Link,
               source: Address) -> None:
        """An announcement for no route: a far peer's roster, or nothing this side takes."""
        if header.topic_id != ROSTER_ID:
            return
        for opener in list(self.openers.values()):
            cipher = opener.keys.opener(header.epoch)
            if cipher is None:
                continue
            try:
                body = cipher.open(bytes(frame[:envelope.SIZE]), bytes(frame[envelope.SIZE:]))
            except CipherError:
                continue
            try:
                message = parse(body)
                kind, key, names = _read(message)
            except (ControlError, ValueError) as exc:
                self.router.link_drop(link, Drop.BAD_ANNOUNCEMENT, f"a roster from {source}: "
                                                                   f"{exc}")
                return
            window = self._window(opener, kind, key, link)
            if window is not None and window.replayed(header, body) is None:
                self.router.link_drop(link, Drop.DUPLICATE, f"a roster of names from {source}")
            elif window is not None:
                self._roster(kind, key, names, link, source)
            return
        self.router.link_drop(link, Drop.AUTH_FAILED, f"a roster of names from {source}")

    def _window(self, opener: Route, kind: str, key: str, link: Link) -> Route | None:
        """The replay window of the far side's roster ``(kind, key)`` (None: past the bound of
        rosters, refused)."""
        with self._lock:
            place = (id(opener), kind, key)
            window = self._windows.get(place)
            if window is None and len(self._windows) >= MAX_ROSTERS:
                self._refuse(link, key, f"more than {MAX_ROSTERS} links of names announced")
                return None
            if window is None:
                window = self._windows[place] = Route(opener.entry, ROSTER_ID, None,
                                                      opener.keys, self.router.warner,
                                                      opener.label)
            return window

    def _roster(self, kind: str, key: str, names: dict[str, Any], link: Link,
                source: Address) -> None:
        """A far peer's names on one of its links: a route here for each one this side's
        patterns take, none for those it no longer announces; or its ask for this side's
        servers (they are told to where it came from)."""
        if kind == ASK:
            for sending in list(self._links.values()):
                if sending.kind == "services" and sending.link is link and sending.to != source:
                    sending.to = source  # told now; after that every 2 s, however often asked
                    self._send(sending)
            return
        roster = (kind, key)
        with self._lock:
            self.rosters[roster] = time.monotonic()
            if len(names) > MAX_NAMES:
                self._refuse(link, key, f"{len(names)} names in one roster, more than "
                                        f"{MAX_NAMES}")
                names = dict(list(names.items())[:MAX_NAMES])
            for (made_kind, far), made in list(self.made.items()):
                if made.roster == roster and far not in names:
                    self._unmake((made_kind, far), "no longer announced")
            for far, item in names.items():
                if (kind, far) not in self.made:
                    self._make(kind, far, item, roster, link)

    def _make(self, kind: str, far: str, item: Any, roster: tuple[str, str],
              link: Link) -> None:
        try:
            announce.read(item)  # its type, hash and QoS as an entry's announcement says them
            well_formed = (isinstance(far, str) and len(far) <= ROS_NAME_MAX
                           and _NAME.fullmatch(far) is not None
                           and _TYPES[kind].fullmatch(item["type"]) is not None)
        except (ValueError, TypeError, KeyError):
            well_formed = False
        if not well_formed:
            self.router.link_drop(link, Drop.BAD_ANNOUNCEMENT, f"a roster's name {far!r:.80}")
            return
        type_name = item["type"]
        taken = self._pattern_of(kind, far, type_name)
        if taken is None:
            return  # this side's file does not take it: its frames count as unknown_topic
        p, local = taken
        if sum(1 for m in self.made.values() if m.pattern is p) >= p.entry.max_routes:
            self._refuse(link, far, f"{kind}[{p.index}] {p.name}: {local} is refused: the "
                                    f"pattern has made its {p.entry.max_routes} routes "
                                    "(max_routes)")
            return
        try:
            spec = self.role.bridge.resolver.found(p, local, type_name)
        except ConfigError as exc:  # its type is not installed here (the package named)
            fix = f" ({exc.fix})" if exc.fix else ""
            self._refuse(link, far, f"{local} from the peer cannot be bridged: {exc.message}"
                                    f"{fix}", Drop.TYPE_NOT_INSTALLED)
            return
        route = self.router.route(spec, topic_id_for(far), f"{local} (from {self.cfg.peer})",
                                  link if kind == "services" else NoLink(), fixed(spec.address),
                                  self.keys_of(spec, None))
        assert isinstance(route, ReceiveRoute | CallerRoute)
        if isinstance(route, ReceiveRoute):
            route.check.expect(route.drop)
            self.heard_from.append(route)
        else:
            self.callers.append(route)
        self.router.far(route, item)
        self.made[(kind, far)] = Made(route, p, roster, local)
        self._pair(local)
        log.info("%s: %s[%d] %s: the peer announces %s (%s): bridged as %s", self.cfg.name,
                 kind, p.index, p.name, far, type_name, local)

    def _pattern_of(self, kind: str, far: str, type_name: str) -> tuple[Pattern, str] | None:
        """The first pattern of this side that takes the far name ``far``, and its name
        here."""
        entries = self.cfg.topics if kind == "topics" else self.cfg.services
        listed = {getattr(e, kind[:-1]) for e in entries if not e.pattern}
        for p in self.taking[kind]:
            local = far_name(p.entry.remote, p.name, far)
            if (matches(p.entry.remote, far) and local not in listed
                    and not denied(local, p.entry.deny) and not denied(local, self.cfg.deny)
                    and p.entry.type in ("", type_name)):
                return p, local
        return None

    def _unmake(self, made_key: tuple[str, str], why: str) -> None:
        made = self.made.pop(made_key)
        for routes in (self.heard_from, self.callers):
            if made.route in routes:
                routes.remove(made.route)  # type: ignore[arg-type]
        self.router.remove(made.route)
        log.info("%s: %s is %s by the peer: its route is removed", self.cfg.name, made.local,
                 why)

    def _refuse(self, link: Link, name: str, sentence: str,
                reason: Drop = Drop.TOO_MANY_NAMES) -> None:
        """A name (or a roster) refused: counted and said once (a roster repeats it)."""
        if (reason.value, name) not in self.refusals.said:
            self.router.link_drop(link, reason, name)
        self.refusals.refuse(reason.value, name, f"{self.cfg.name}: {sentence}")

    def _pair(self, local: str) -> None:
        """A name sent and received here: its routes share an echo guard."""
        sent = self.sent.get(local)
        got = next((m.route for m in self.made.values() if m.local == local
                    and isinstance(m.route, ReceiveRoute)), None)
        if sent is not None and got is not None and sent.echo is None:
            sent.echo = got.echo = EchoGuard()

    # -- both ----------------------------------------------------------------------------------
    def _loop(self) -> None:
        """Rosters sent (often while the bridge is young); rosters unheard too long expire."""
        quiet = max(self.cfg.pattern_grace, self.quiet)
        last = 0.0
        while not self.role.life.stopping.wait(ANNOUNCE_FAST):
            now = time.monotonic()
            if now - self._born < YOUNG or now - last >= ANNOUNCE_EVERY:
                last = now
                self._tell()
            with self._lock:
                for roster in [r for r, heard in self.rosters.items() if now - heard > quiet]:
                    del self.rosters[roster]
                    for made_key in [k for k, m in self.made.items() if m.roster == roster]:
                        self._unmake(made_key, f"not heard of for {quiet:g} s")

    def status(self) -> dict[str, Any]:
        found: dict[str, Any] = {"found": [], "refused": dict(self.refusals.counts)}
        for finder in (self.discovery, self.service_discovery):
            each = finder.status()
            found["found"] += each["found"]
            for reason, count in each["refused"].items():
                found["refused"][reason] = found["refused"].get(reason, 0) + count
        with self._lock:
            found["found"] = sorted([*found["found"], *(m.local for m in self.made.values())])
        return found


def _read(message: dict[str, Any]) -> tuple[str, str, dict[str, Any]]:
    """A roster's kind, link and names; ValueError when it is not one."""
    kind, key, names = message.get("kind"), message.get("link"), message.get("names")
    if (kind not in (*_TYPES, ASK) or not isinstance(key, str) or len(key) > 100
            or not isinstance(names, dict)):
        raise ValueError("not a roster: no kind, link or names")
    return kind, key, names


def _cipher(spec: TopicSpec | ServiceSpec) -> Any:
    assert spec.cipher is not None
    return spec.cipher
