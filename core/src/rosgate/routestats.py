"""What a bridge's routes counted, said: the numbers of the status snapshot, the log lines when
routes end, and the warnings of receiving topics gone silent. Housekeeping, never on a
message's path: the router hands its routes over (:meth:`rosgate.router.Router.stats`)."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import Any

from .config import BridgeConfig
from .routes import ReceiveRoute, Route, TransmitRoute

log = logging.getLogger("rosgate")


def warn_stale(routes: Iterable[Route], config: BridgeConfig, now: float) -> None:
    """A warning for each receiving route silent for ``stale_after`` seconds (once more per
    ``stale_after`` of silence, at most ``stale_warnings`` times)."""
    for route in routes:
        if not isinstance(route, ReceiveRoute):
            continue
        silence = now - route.last_received
        due = config.stale_after * (route.stale_warnings_given + 1)
        if silence >= due and route.stale_warnings_given < config.stale_warnings:
            route.stale_warnings_given += 1
            log.warning("%s: no data for %.0f s (warning %d of %d)", route.label, silence,
                        route.stale_warnings_given, config.stale_warnings)


def stats(routes: Iterable[Route], link_drops: Mapping[Any, int]) -> dict[str, Any]:
    """Counters per route, plus drops that belong to no topic."""
    counted = {}
    for r in routes:
        counted[r.label] = r.counters.snapshot()
        if isinstance(r, TransmitRoute):
            counted[r.label]["queue_depth"] = r.queue_depth
    return {"routes": counted, "link_drops": dict(link_drops)}


def log_stats(routes: Iterable[Route], link_drops: Mapping[Any, int] | None = None) -> None:
    """Log the counters of ``routes`` (and the frames for no topic, when given)."""
    for route in routes:
        c = route.counters
        drops = ", ".join(f"{k}={v}" for k, v in sorted(c.drops.items())) or "none"
        lost = f", lost on the way {c.lost}" if c.lost else ""
        log.info("%s: sent %d (%d B), received %d (%d B)%s%s, drops: %s", route.label,
                 c.sent, c.bytes_sent, c.received, c.bytes_received, lost,
                 _real_link_counters(route), drops)
    if link_drops:
        log.info("frames for no topic: %s", dict(link_drops))


def _real_link_counters(route: Route) -> str:
    """The counters of real links that say something (wire, repairs, compression, queue)."""
    c = route.counters
    depth = route.queue_depth if isinstance(route, TransmitRoute) else 0
    parts = [(c.bytes_on_wire not in (0, c.bytes_sent), f"on the wire {c.bytes_on_wire} B"),
             (c.retransmitted, f"retransmitted {c.retransmitted}"),
             (c.recovered, f"recovered {c.recovered}"),
             (c.bytes_before_compression, f"compressed {c.bytes_before_compression} B -> "
              f"{c.bytes_after_compression} B ({c.not_compressed} sent as they were)"),
             (depth, f"queued {depth}")]
    return "".join(f", {part}" for shown, part in parts if shown)
