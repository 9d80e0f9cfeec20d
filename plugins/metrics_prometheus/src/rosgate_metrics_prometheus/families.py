"""What the ``metrics`` monitor serves: a bridge's status as Prometheus families, built afresh
at each scrape. Imported when the monitor starts (prometheus_client takes a while to import)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

ENTRY_LABELS = ["bridge", "kind", "topic", "direction", "peer"]
#: per entry: (status field, family name, help)
ENTRY_COUNTERS = (
    ("sent", "rosgate_messages_sent", "Messages this bridge sent to the peer"),
    ("received", "rosgate_messages_received", "Messages this bridge received from the peer"),
    ("bytes_sent", "rosgate_bytes_sent", "Bytes of the frames sent"),
    ("bytes_received", "rosgate_bytes_received", "Bytes of the frames received"),
    ("lost", "rosgate_messages_lost", "Messages lost on the way (sequence gaps)"),
)
LINK_COUNTERS = (
    ("bytes_out", "rosgate_link_bytes_sent", "Bytes a link put on the wire"),
    ("bytes_in", "rosgate_link_bytes_received", "Bytes a link took from the wire"),
    ("frames_out", "rosgate_link_frames_sent", "Frames a link sent"),
    ("frames_in", "rosgate_link_frames_received", "Frames a link received"),
)


#: the most link labels a bridge's metrics carry: past them, connections share OTHER_LINKS
MAX_LINK_LABELS = 1000
OTHER_LINKS = "main<-other"


def link_label(name: str) -> str:
    """A link's label: its name, without the far end's port where the far end dialled in
    (``main<-192.168.1.7:58102`` -> ``main<-192.168.1.7``): a reconnect's new port would start
    a new series each time."""
    head, arrow, far = name.rpartition("<-")
    return f"{head}{arrow}{far.rpartition(':')[0]}" if arrow and ":" in far else name


class LinkTotals:
    """Link counters by label, across the connections that came and went under it: a label's
    counter is what its connections that closed carried plus what the open ones carry now, so
    it only grows."""

    def __init__(self) -> None:
        self.closed: dict[str, dict[str, int]] = {}  # label -> field -> carried by closed links
        self.last: dict[str, dict[str, Any]] = {}  # link name -> its last status

    def add(self, links: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
        now = {link["name"]: link for link in links}
        for name, link in self.last.items():
            if name not in now:
                carried = self.closed.setdefault(self._label(name), {})
                for field, _, _ in LINK_COUNTERS:
                    carried[field] = carried.get(field, 0) + link[field]
        self.last = now
        rows: dict[str, dict[str, Any]] = {}
        for label, carried in self.closed.items():
            rows[label] = {"up": 0, "queue": 0, **carried}
        for name, link in now.items():
            row = rows.setdefault(self._label(name), {"up": 0, "queue": 0})
            row["up"] = max(row["up"], int(link["up"]))
            row["queue"] += link["queue"]
            for field, _, _ in LINK_COUNTERS:
                row[field] = row.get(field, 0) + link[field]
        return rows

    def _label(self, name: str) -> str:
        label = link_label(name)
        if label in self.closed or len(self.closed) < MAX_LINK_LABELS or label == name:
            return label
        return OTHER_LINKS


class StatusCollector(Collector):
    """The families of one bridge's status, read at each scrape."""

    def __init__(self, status: Callable[[], dict[str, Any]]):
        self.status = status
        self.links = LinkTotals()

    def collect(self) -> Iterator[Any]:
        status = self.status()
        bridge = status["bridge"]
        entries = [e for e in status["entries"] if e["refused"] is None]
        yield from entry_families(bridge, entries)
        refused = GaugeMetricFamily("rosgate_entry_refused", "1 for an entry the peer refused",
                                    labels=ENTRY_LABELS)
        for e in status["entries"]:
            if e["refused"] is not None:
                refused.add_metric(_labels(bridge, e), 1)
        yield refused
        yield from link_families(bridge, status, self.links.add(status["links"]))
        uptime = GaugeMetricFamily("rosgate_uptime_seconds", "Seconds since the bridge started",
                                   labels=["bridge"])
        uptime.add_metric([bridge], status["uptime"])
        yield uptime


def _labels(bridge: str, e: dict[str, Any]) -> list[str]:
    return [bridge, e["kind"], e["name"], str(e["direction"]), str(e["peer"])]


def entry_families(bridge: str, entries: list[dict[str, Any]]) -> Iterator[Any]:
    for field, name, doc in ENTRY_COUNTERS:
        family = CounterMetricFamily(name, doc, labels=ENTRY_LABELS)
        for e in entries:
            family.add_metric(_labels(bridge, e), e[field])
        yield family
    drops = CounterMetricFamily("rosgate_drops", "Messages dropped, by reason",
                                labels=[*ENTRY_LABELS, "reason"])
    queue = GaugeMetricFamily("rosgate_queue_depth", "Messages waiting to be sent",
                              labels=ENTRY_LABELS)
    stale = GaugeMetricFamily("rosgate_topic_stale", "1 while a receiving topic is stale",
                              labels=ENTRY_LABELS)
    for e in entries:
        labels = _labels(bridge, e)
        for reason, count in sorted(e["drops"].items()):
            drops.add_metric([*labels, reason], count)
        queue.add_metric(labels, e["queue"])
        if e["stale"] is not None:
            stale.add_metric(labels, int(e["stale"]))
    yield from (drops, queue, stale)


def link_families(bridge: str, status: dict[str, Any],
                  links: dict[str, dict[str, Any]]) -> Iterator[Any]:
    up = GaugeMetricFamily("rosgate_link_up", "1 while a link is up", labels=["bridge", "link"])
    queue = GaugeMetricFamily("rosgate_link_queue_depth", "Messages waiting in a link",
                              labels=["bridge", "link"])
    counters = [(field, CounterMetricFamily(name, doc, labels=["bridge", "link"]))
                for field, name, doc in LINK_COUNTERS]
    for label, link in links.items():
        labels = [bridge, label]
        up.add_metric(labels, link["up"])
        queue.add_metric(labels, link["queue"])
        for field, family in counters:
            family.add_metric(labels, link[field])
    peers = GaugeMetricFamily("rosgate_peer_up", "1 while a peer is up", labels=["bridge", "peer"])
    for p in status["peers"]:
        if p["up"] is not None:
            peers.add_metric([bridge, str(p["name"])], int(p["up"]))
    lost = CounterMetricFamily("rosgate_frames_for_no_topic", "Frames no topic took, by reason",
                               labels=["bridge", "reason"])
    for reason, count in sorted(status["link_drops"].items()):
        lost.add_metric([bridge, reason], count)
    yield from (up, queue, *(family for _, family in counters), peers, lost)
