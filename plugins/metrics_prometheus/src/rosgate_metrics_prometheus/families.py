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


class StatusCollector(Collector):
    """The families of one bridge's status, read at each scrape."""

    def __init__(self, status: Callable[[], dict[str, Any]]):
        self.status = status

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
        yield from link_families(bridge, status)
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


def link_families(bridge: str, status: dict[str, Any]) -> Iterator[Any]:
    up = GaugeMetricFamily("rosgate_link_up", "1 while a link is up", labels=["bridge", "link"])
    queue = GaugeMetricFamily("rosgate_link_queue_depth", "Messages waiting in a link",
                              labels=["bridge", "link"])
    counters = [(field, CounterMetricFamily(name, doc, labels=["bridge", "link"]))
                for field, name, doc in LINK_COUNTERS]
    for link in status["links"]:
        labels = [bridge, link["name"]]
        up.add_metric(labels, int(link["up"]))
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
