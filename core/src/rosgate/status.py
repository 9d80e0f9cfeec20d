"""A running bridge's status: every topic, service and link with its counters, as one plain,
JSON-ready mapping — what ``rosgate top``, ``/diagnostics``, metrics and the summary line read.

Fields (counters only grow; rates are differences between two statuses over their ``time``)::

    version    1 (a field may be added; none is renamed)
    bridge     this bridge's name          role     client | server | peer
    time       seconds (monotonic clock)   uptime   seconds since the bridge started
    entries    one per topic and service route, and per entry the peer refused:
        kind        topic | service        name       the ROS name on this side
        direction   transmit | receive     peer       the other side's name (or address)
        type        pkg/msg/Type           transport  udp, tcp...      port   int or null
        sent, bytes_sent, received, bytes_received, lost     counters
        drops       {reason: count}        queue      messages waiting to be sent
        shedding    a best-effort topic's queue in this bridge (its subscription's, or the
                    receive buffer) stands behind now, and its oldest messages are dropped
        stale       receiving topics: no message for bridge.stale_after seconds (else null)
        silence     receiving topics: seconds since the last message (else null)
        latency     seconds from sender to publish, where known (else null)
        refused     why the peer refused this entry (policy, type), or null
        pattern     the pattern entry that made this route as it is written (`/robot1/**`;
                    on a server, its client's pattern), or null: a listed entry
    peers      [{name, up (true, false, or null: unknown)}]
    links      [{name, up, frames_out, bytes_out, packets_out, frames_in, bytes_in, packets_in,
                 queue, bandwidth (bit/s budget, or null), rtt (seconds, or null)}]
    link_drops {reason: count} of frames that belonged to no topic
    patterns   what pattern entries found (names) and refused ({reason: count}): a client's,
               and a peer's on a bus
"""

from __future__ import annotations

import time
from typing import Any

from .config import BridgeConfig, ServiceConfig, TopicConfig
from .links.base import Link
from .links.lifetime import Lifetime
from .monitor import Status
from .roles import Role
from .roles.client import ClientRole
from .roles.peer import PeerRole
from .roles.server import ServerRole
from .router import Router
from .routes import ReceiveRoute, Route, TransmitRoute
from .streamlink.slot import LinkSlot

VERSION = 1


def collect(config: BridgeConfig, role: Role | None, router: Router | None, life: Lifetime,
            started: float) -> Status:
    now = time.monotonic()
    routes = router.snapshot() if router is not None else []
    peers_of, made_by = _peers_of_routes(role, routes), _made_by(role)
    entries = [_entry(r, peers_of.get(id(r), _peer_in_label(r.label)), config, now,
                      made_by.get(id(r.entry)))
               for r in routes]
    entries += _refused(role)
    return {"version": VERSION, "bridge": config.name, "role": str(config.role), "time": now,
            "uptime": now - started, "entries": entries, "peers": _peers(role, config),
            "links": _links(life.links()),
            "link_drops": dict(router.link_drops) if router is not None else {},
            "patterns": _patterns(role)}


def _patterns(role: Role | None) -> Status:
    """What pattern entries found (names) and refused (by reason, each name once)."""
    total: Status = {"found": [], "refused": {}}
    finders = [getattr(role, name, None)
               for name in ("discovery", "service_discovery", "action_discovery")]
    for discovery in [*finders, *(role.bus_patterns if isinstance(role, PeerRole) else [])]:
        if discovery is not None:
            each = discovery.status()
            total["found"] += each["found"]
            for reason, count in each["refused"].items():
                total["refused"][reason] = total["refused"].get(reason, 0) + count
    return total


def _made_by(role: Role | None) -> dict[int, str]:
    """The pattern (as written) that made each route, by ``id`` of the route's entry."""
    if isinstance(role, ClientRole):
        return {id(f.route.config): f.pattern.name for f in role.founds() if f.route is not None}
    if isinstance(role, PeerRole):
        return {id(spec.config): found.pattern.name for found in role.bus_patterns
                for spec in list(found.made.values())}
    if isinstance(role, ServerRole):
        return {id(route.entry): pattern for s in list(role.sessions.values())
                for index, pattern in list(s.made_by.items())
                if (route := s.by_index.get(index)) is not None}
    return {}


#: an entry's counters before anything crossed, and its state when nothing is wrong
IDLE = {"sent": 0, "bytes_sent": 0, "received": 0, "bytes_received": 0, "lost": 0, "drops": {},
        "queue": 0, "shedding": False, "stale": None, "silence": None, "latency": None,
        "refused": None}


def _row(e: TopicConfig | ServiceConfig | None, name: str, peer: str, **state: Any) -> Status:
    return {"kind": "service" if isinstance(e, ServiceConfig) else "topic", "name": name,
            "direction": str(e.direction) if e else None, "peer": peer,
            "type": e.type if e else None, "transport": e.transport if e else None,
            "port": e.port if e else None, **IDLE, "drops": {}, "pattern": None, **state}


def _name(e: TopicConfig | ServiceConfig) -> str:
    return e.topic if isinstance(e, TopicConfig) else e.service


def _entry(route: Route, peer: str, config: BridgeConfig, now: float,
           pattern: str | None) -> Status:
    c = route.counters
    silence = now - route.last_received if isinstance(route, ReceiveRoute) else None
    return _row(route.entry, _name(route.entry), peer, sent=c.sent, bytes_sent=c.bytes_sent,
                received=c.received, bytes_received=c.bytes_received, lost=c.lost,
                drops=dict(c.drops),
                queue=route.queue_depth if isinstance(route, TransmitRoute) else 0,
                shedding=route.shedding,
                stale=silence >= config.stale_after if silence is not None else None,
                silence=silence, pattern=pattern)


def _peer_in_label(label: str) -> str:
    """The peer a route's label names: ``/chatter (to robot1)`` -> ``robot1``."""
    _, _, rest = label.rpartition(" (")
    return rest.rstrip(")").partition(" ")[2] or "?"


def _peers_of_routes(role: Role | None, routes: list[Route]) -> dict[int, str]:
    if isinstance(role, ServerRole):
        return {id(r): s.name for s in list(role.sessions.values()) for r in s.routes}
    if isinstance(role, ClientRole) and role.server_name:
        return {id(r): role.server_name for r in routes}
    return {}


def _refused(role: Role | None) -> list[Status]:
    """Entries the other side refused (its policy, a type it does not know): no route here."""
    if isinstance(role, ClientRole):
        return [_row(None, name, role.server_name or "server", refused=why)
                for name, why in role.refused.items()]
    out = []
    for s in list(role.sessions.values()) if isinstance(role, ServerRole) else []:
        for index, why in list(s.refused.items()):
            e = s.entries[index] if index < len(s.entries) else None
            out.append(_row(e, _name(e) if e else str(index), s.name, refused=why))
    return out


def _peers(role: Role | None, config: BridgeConfig) -> list[Status]:
    if isinstance(role, ClientRole):
        return [{"name": role.server_name or config.server, "up": role.connected.is_set()}]
    if isinstance(role, ServerRole):
        return [{"name": s.name, "up": s.down_since is None}
                for s in list(role.sessions.values())]
    if isinstance(role, PeerRole) and config.peer:
        up = role.handshake.up.is_set() if role.handshake is not None else None
        return [{"name": config.peer, "up": up}]
    return []


def _links(links: list[Link]) -> list[Status]:
    inside = {id(link.current) for link in links
              if isinstance(link, LinkSlot) and link.current is not None}
    out = []
    for link in links:
        if id(link) in inside:
            continue  # shown as its slot, which stays when the connection goes
        c = link.counters
        current = link.current if isinstance(link, LinkSlot) else link
        up = current is not None and not current.closed.is_set()
        budget = getattr(current, "budget", None)
        queued = getattr(current, "queued", None)
        out.append({"name": link.name, "up": up, "frames_out": c.frames_out,
                    "bytes_out": c.bytes_out, "packets_out": c.packets_out,
                    "frames_in": c.frames_in, "bytes_in": c.bytes_in, "packets_in": c.packets_in,
                    "queue": (link.waiting if isinstance(link, LinkSlot) else 0)
                    + (queued() if queued is not None and up else 0),
                    "bandwidth": budget.bandwidth if budget is not None else None, "rtt": None})
    return out


# -- the summary line ------------------------------------------------------------------------

def _key(e: Status) -> tuple[Any, ...]:
    return e["kind"], e["name"], e["direction"], e["peer"]


def summary(now: Status, before: Status | None) -> str:
    """One line for the log: totals since ``before`` (or the start), and what is abnormal."""
    entries = [e for e in now["entries"] if e["refused"] is None]
    old = {_key(e): e for e in (before or {}).get("entries", [])}
    span = now["time"] - before["time"] if before else now["uptime"]
    totals: dict[str, int] = {}
    drops: dict[str, int] = {}
    for e in entries:
        o = old.get(_key(e), IDLE)
        for key in ("sent", "received", "bytes_sent", "bytes_received"):
            totals[key] = totals.get(key, 0) + int(e[key] - o[key])
        for reason, n in e["drops"].items():
            n -= o["drops"].get(reason, 0)
            if n:
                drops[reason] = drops.get(reason, 0) + n
    topics = sum(e["kind"] == "topic" for e in entries)
    volume = totals.get("bytes_sent", 0) + totals.get("bytes_received", 0)
    parts = [f"{now['bridge']}: last {span:.0f} s: {topics} topic(s), "
             f"{len(entries) - topics} service(s), sent {totals.get('sent', 0)}, received "
             f"{totals.get('received', 0)} ({_size(volume)})"]
    if drops:
        parts.append("drops " + ", ".join(f"{k}={v}" for k, v in sorted(drops.items())))
    for word, names in (
            ("stale", [e["name"] for e in entries if e["stale"]]),
            ("down", [str(p["name"]) for p in now["peers"] if p["up"] is False]),
            ("refused", [e["name"] for e in now["entries"] if e["refused"] is not None])):
        if names:
            parts.append(f"{word} " + ", ".join(sorted(names)))
    return "; ".join(parts)


def _size(n: float) -> str:
    for unit in ("B", "kB", "MB"):
        if abs(n) < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"
