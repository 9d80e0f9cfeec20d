"""A peer's topic patterns. A transmit pattern finds the publishers on this side's graph
(:class:`~rosgate.discovery.Discovery`, as a client's) and makes a route per name, on the
entry's own link (its ``port``: every name it finds shares it, told apart by the envelope's
topic id, derived from the name as a listed entry's). The far peer learns the names from the
link's *roster*: an announcement (``FLAG_ANNOUNCE``) under the id of :data:`ROSTER_NAME`, sealed
like the entry's frames, that lists every name the link carries with its type and RIHS01 hash,
sent when a name appears or goes and every :data:`~rosgate.announce.ANNOUNCE_EVERY` seconds.

The receiving peer makes a route for an announced name only if one of its own receive patterns
takes it (its ``remote:`` matches, not denied, within ``max_routes``): a peer never publishes a
name its own file does not take. A name left out of the roster (gone past the far side's
``pattern_grace``), or a roster unheard for longer than the far peer may be silent, takes its
route down: the publisher here is destroyed. A name both sent and received here (a publisher on
each side) never echoes back: :mod:`rosgate.echo`.
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

from ..announce import ANNOUNCE_EVERY, ANNOUNCE_FAST, YOUNG
from ..config import Direction
from ..config.kinds import ROS_NAME_MAX
from ..config.patterns import denied, far_name, matches
from ..discovery import Discovery, Found, Refusals
from ..drops import Drop
from ..echo import EchoGuard
from ..errors import CipherError, ConfigError
from ..keyring import Keys, NoKey, StaticKeys
from ..links import Link
from ..router import fixed
from ..routes import ReceiveRoute, Route, TransmitRoute
from ..spec import ServiceSpec, TopicSpec
from ..streamlink import Connector
from ..transport import Address, StreamTransport
from ..wire import envelope
from ..wire.control import ControlError, parse
from ..wire.envelope import topic_id_for
from . import NoLink, Role

if TYPE_CHECKING:
    from ..resolver import Pattern

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
_TYPE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*/msg/[A-Za-z_][A-Za-z0-9_]*")


@dataclass
class Sending:
    """One link's roster: the names this side's transmit patterns carry on it."""

    route: Route  # seals the roster (its keys, its sequence)
    link: Link
    to: Address
    key: str  # how the far side tells this link's roster from another's
    seq: Iterator[int] = field(default_factory=lambda: itertools.count(1))
    names: dict[str, dict[str, Any]] = field(default_factory=dict)  # far name -> item


@dataclass
class Made:
    """A receiving route a far peer's roster made here."""

    route: ReceiveRoute
    pattern: Pattern
    roster: str  # the roster that announced it


class PeerPatterns:
    """The topic patterns of a peer ``role``: ``keys_of`` keys a route as the role's listed
    entries; ``heard_from`` the receiving routes whose far side is the peer; ``quiet``: seconds
    the peer may be silent before the names it announced are taken down."""

    def __init__(self, role: Role, keys_of: KeysOf, heard_from: list[Route], quiet: float):
        self.role, self.cfg, self.router = role, role.cfg, role.router
        self.keys_of, self.heard_from, self.quiet = keys_of, heard_from, quiet
        plan = role.bridge.plan
        self.sending: dict[int, Sending] = {}  # by the transmit pattern's index
        self._links: dict[tuple[str, Address], Sending] = {}
        self.taking = [p for p in plan.patterns if p.section == "topics"
                       and p.entry.direction is Direction.RECEIVE]
        self.openers: list[Route] = []  # one per cipher of the receive patterns: opens rosters
        self.discovery = Discovery(self.cfg, plan.patterns, self.router.ros.node, self._add,
                                   self._drop, time.monotonic, self._tell)
        self.made: dict[str, Made] = {}  # far name -> its route here
        self.rosters: dict[str, float] = {}  # roster key -> when last heard
        self.sent: dict[str, TransmitRoute] = {}  # local name -> its transmitting route
        self.refusals = Refusals()
        self._lock = threading.RLock()
        self._born = time.monotonic()

    def start(self) -> None:
        for p in self.discovery.patterns:
            self.sending[p.index] = self._sending(p)
        for p in self.taking:
            self._taking(p)
        if self.taking:
            self.router.on_unknown_announcement = self._heard
        self.discovery.start()
        if self.sending or self.taking:
            threading.Thread(target=self._loop, name="peer-patterns", daemon=True).start()

    def stop(self) -> None:
        self.discovery.stop()

    # -- sending -----------------------------------------------------------------------------
    def _spec(self, p: Pattern) -> TopicSpec:
        spec = p.checked
        assert isinstance(spec, TopicSpec)
        if spec.key is not None:
            raise self.cfg.error(f"topics[{p.index}].transport", f"{spec.transport.name} is a "
                                 "bus: it finds the names itself, a peer's pattern does not",
                                 "list each topic, or use a point-to-point link (udp, tcp)")
        return spec

    def _sending(self, p: Pattern) -> Sending:
        """The link a transmit pattern's routes share (one per port), and its roster."""
        spec = self._spec(p)
        where = (spec.transport.name, spec.address)
        if where in self._links:
            return self._links[where]
        link: Link
        if isinstance(spec.transport, StreamTransport):
            link = slot = self.role.bridge.slot(f"{spec.transport.name}->{self.cfg.peer}:"
                                                f"{spec.address[1]}")
            Connector(spec.transport, spec.address, slot, self.router.on_frame,
                      self.router.on_lost, self.role.life, self.role.bridge.backoff,
                      budget=self.role.bridge.budget(spec.transport)).start()
        else:
            link = self.role.datagram_link(spec.transport, spec.local, f"topics[{p.index}].port",
                                           sources=self.role.sources(spec.transport,
                                                                     self.cfg.peer))
        keys = self.keys_of(spec, ROSTER_NAME) or StaticKeys(_cipher(spec))
        route = Route(spec.config, ROSTER_ID, None, keys, self.router.warner,
                      f"names on {link.name}")
        sending = self._links[where] = Sending(route, link, spec.address,
                                               f"{spec.transport.name}:{spec.address[1]}")
        return sending

    def _add(self, found: Found) -> TransmitRoute | None:
        """A name a transmit pattern found: said in its link's roster first (so the far side's
        route is there for its first message), then its route."""
        try:
            spec = self.role.bridge.resolver.found(found.pattern, found.name, found.type)
        except ConfigError as exc:
            log.error("%s: %s cannot be bridged: %s", self.cfg.name, found.name, exc)
            return None
        sending = self.sending[found.pattern.index]
        with self._lock:
            sending.names[spec.config.remote] = self.router.entry_item(spec)
        self._send(sending)
        route = self.router.route(spec, topic_id_for(spec.config.remote), spec.name,
                                  sending.link, fixed(spec.address), self.keys_of(spec, None))
        assert isinstance(route, TransmitRoute)
        with self._lock:
            self.sent[found.name] = route
            self._pair(found.name)
        return route

    def _drop(self, found: Found) -> None:
        sending = self.sending[found.pattern.index]
        with self._lock:
            sending.names.pop(found.route.topic.remote, None)
            self.sent.pop(found.name, None)
        self.router.remove(found.route)

    def _tell(self) -> None:
        for sending in list(self._links.values()):
            self._send(sending)

    def _send(self, sending: Sending) -> None:
        with self._lock:
            body = json.dumps({"link": sending.key, "names": sending.names},
                              separators=(",", ":")).encode()
        route = sending.route
        try:
            frame = route.seal(envelope.FLAG_ANNOUNCE, route.keys.epoch(),
                               next(sending.seq), body)
        except (NoKey, CipherError):
            return  # before the handshake: the next roster comes soon
        sending.link.send(frame, route.announcer, sending.to)

    # -- receiving ---------------------------------------------------------------------------
    def _taking(self, p: Pattern) -> None:
        """A receive pattern's link bound (or listened on), and an opener for its cipher."""
        spec = self._spec(p)
        sources = self.role.sources(spec.transport, self.cfg.peer)
        key = f"topics[{p.index}].port"
        if isinstance(spec.transport, StreamTransport):
            self.role.listen(spec.transport, spec.address, self.router.on_frame, key,
                             sources=sources)
        else:
            self.role.datagram_link(spec.transport, spec.address, key, sources=sources)
        if all(o.entry.cipher != p.entry.cipher for o in self.openers):
            keys = self.keys_of(spec, ROSTER_NAME) or StaticKeys(_cipher(spec))
            self.openers.append(Route(spec.config, ROSTER_ID, None, keys, self.router.warner,
                                      f"names from {self.cfg.peer}"))

    def _heard(self, header: envelope.Header, frame: bytes, link: Link,
               source: Address) -> None:
        """An announcement for no route: a far peer's roster, or nothing this side takes."""
        if header.topic_id != ROSTER_ID:
            return
        for opener in self.openers:
            cipher = opener.keys.opener(header.epoch)
            if cipher is None:
                continue
            try:
                body = cipher.open(bytes(frame[:envelope.SIZE]), bytes(frame[envelope.SIZE:]))
            except CipherError:
                continue
            if opener.replayed(header, body) is None:
                self.router.link_drop(link, Drop.DUPLICATE, f"a roster of names from {source}")
                return
            try:
                self._roster(parse(body), link)
            except (ControlError, ValueError, TypeError) as exc:
                self.router.link_drop(link, Drop.BAD_ANNOUNCEMENT, f"a roster from {source}: "
                                                                   f"{exc}")
            return
        self.router.link_drop(link, Drop.AUTH_FAILED, f"a roster of names from {source}")

    def _roster(self, message: dict[str, Any], link: Link) -> None:
        """A far peer's names on one of its links: a route here for each one a receive pattern
        takes, none for those it no longer announces."""
        key, names = message.get("link"), message.get("names")
        if not isinstance(key, str) or len(key) > 100 or not isinstance(names, dict):
            raise ValueError("not a roster: no link or names")
        with self._lock:
            if key not in self.rosters and len(self.rosters) >= MAX_ROSTERS:
                self._refuse(link, key, f"more than {MAX_ROSTERS} links of names announced")
                return
            self.rosters[key] = time.monotonic()
            if len(names) > MAX_NAMES:
                self._refuse(link, key, f"{len(names)} names in one roster, more than "
                                        f"{MAX_NAMES}")
                names = dict(list(names.items())[:MAX_NAMES])
            for far, made in list(self.made.items()):
                if made.roster == key and far not in names:
                    self._unmake(far, "no longer announced")
            for far, item in names.items():
                if far not in self.made:
                    self._make(far, item, key, link)

    def _make(self, far: str, item: Any, roster: str, link: Link) -> None:
        if not (isinstance(far, str) and len(far) <= ROS_NAME_MAX and _NAME.fullmatch(far)
                and isinstance(item, dict) and isinstance(item.get("type"), str)
                and _TYPE.fullmatch(item["type"])):
            self.router.link_drop(link, Drop.BAD_ANNOUNCEMENT, f"a roster's name {far!r:.80}")
            return
        type_name = item["type"]
        taken = self._pattern_of(far, type_name)
        if taken is None:
            return  # this side's file does not take it: its frames count as unknown_topic
        p, local = taken
        if sum(1 for m in self.made.values() if m.pattern is p) >= p.entry.max_routes:
            self._refuse(link, far, f"topics[{p.index}] {p.name}: {local} is refused: the "
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
                                  NoLink(), keys=self.keys_of(spec, None))
        assert isinstance(route, ReceiveRoute)
        route.check.expect(route.drop)
        self.router.far(route, item)
        self.made[far] = Made(route, p, roster)
        self.heard_from.append(route)
        self._pair(local)
        log.info("%s: topics[%d] %s: the peer announces %s (%s): bridged as %s", self.cfg.name,
                 p.index, p.name, far, type_name, local)

    def _pattern_of(self, far: str, type_name: str) -> tuple[Pattern, str] | None:
        """The first receive pattern that takes the far name ``far``, and its name here."""
        listed = {t.topic for t in self.cfg.topics if not t.pattern}
        for p in self.taking:
            local = far_name(p.entry.remote, p.name, far)
            if (matches(p.entry.remote, far) and local not in listed
                    and not denied(local, p.entry.deny) and not denied(local, self.cfg.deny)
                    and p.entry.type in ("", type_name)):
                return p, local
        return None

    def _unmake(self, far: str, why: str) -> None:
        made = self.made.pop(far)
        if made.route in self.heard_from:
            self.heard_from.remove(made.route)
        self.router.remove(made.route)
        log.info("%s: %s is %s by the peer: its route is removed", self.cfg.name,
                 made.route.topic.topic, why)

    def _refuse(self, link: Link, name: str, sentence: str,
                reason: Drop = Drop.TOO_MANY_NAMES) -> None:
        """A name (or a roster) refused: counted and said once (a roster repeats it)."""
        if (reason.value, name) not in self.refusals.said:
            self.router.link_drop(link, reason, name)
        self.refusals.refuse(reason.value, name, f"{self.cfg.name}: {sentence}")

    def _pair(self, local: str) -> None:
        """A name sent and received here: its routes share an echo guard."""
        sent = self.sent.get(local)
        got = next((m.route for m in self.made.values() if m.route.topic.topic == local), None)
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
                for key in [k for k, heard in self.rosters.items() if now - heard > quiet]:
                    del self.rosters[key]
                    for far in [f for f, m in self.made.items() if m.roster == key]:
                        self._unmake(far, f"not heard of for {quiet:g} s")

    def status(self) -> dict[str, Any]:
        found = self.discovery.status()
        with self._lock:
            found["found"] = sorted([*found["found"], *(m.route.topic.topic
                                                        for m in self.made.values())])
        for reason, count in self.refusals.counts.items():
            found["refused"][reason] = found["refused"].get(reason, 0) + count
        return found


def _cipher(spec: TopicSpec) -> Any:
    assert spec.cipher is not None
    return spec.cipher
