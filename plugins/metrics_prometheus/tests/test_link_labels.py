"""Link labels: a client that dials in again and again (a new ephemeral port each time) stays one
series per host, whose counters only grow across its connections."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, generate_latest
from rosgate_metrics_prometheus.families import (
    MAX_LINK_LABELS,
    OTHER_LINKS,
    StatusCollector,
    link_label,
)


def link(name: str, frames: int, up: bool = True) -> dict:
    return {"name": name, "up": up, "queue": 0, "frames_out": frames, "frames_in": frames,
            "bytes_out": 10 * frames, "bytes_in": 10 * frames}


def test_a_dialled_in_link_is_labelled_by_its_host():
    assert link_label("main<-192.168.1.7:58102") == "main<-192.168.1.7"
    assert link_label("main<-::1:40000") == "main<-::1"
    assert link_label("main->192.168.1.20:12000") == "main->192.168.1.20:12000"  # ours: fixed
    assert link_label("main of robot1") == "main of robot1"


def scrape(links: list[dict]) -> tuple[StatusCollector, CollectorRegistry, dict]:
    """A collector over a status the test changes between scrapes."""
    status = {"bridge": "base", "entries": [], "links": links, "peers": [], "link_drops": {},
              "uptime": 1.0}
    registry = CollectorRegistry()
    collector = StatusCollector(lambda: status)
    registry.register(collector)
    return collector, registry, status


def samples(registry: CollectorRegistry) -> dict[str, float]:
    out = {}
    for line in generate_latest(registry).decode().splitlines():
        if line.startswith("rosgate_link_frames_sent_total"):
            key, value = line.rsplit(" ", 1)
            out[key] = float(value)
    return out


def test_reconnects_from_one_host_are_one_series_that_only_grows():
    collector, registry, status = scrape([link("main<-10.0.0.5:50001", 100)])
    assert samples(registry) == {
        'rosgate_link_frames_sent_total{bridge="base",link="main<-10.0.0.5"}': 100.0}
    status["links"] = [link("main<-10.0.0.5:50002", 7)]  # the first closed; a new port
    assert samples(registry) == {
        'rosgate_link_frames_sent_total{bridge="base",link="main<-10.0.0.5"}': 107.0}
    status["links"] = [link("main<-10.0.0.5:50002", 9), link("main<-10.0.0.5:50003", 1)]
    assert samples(registry) == {
        'rosgate_link_frames_sent_total{bridge="base",link="main<-10.0.0.5"}': 110.0}


def test_a_flood_of_hosts_cannot_grow_the_labels_without_bound():
    collector, registry, status = scrape([])
    hosts = [f"main<-10.{n // 256}.{n % 256}.1:4000" for n in range(MAX_LINK_LABELS + 50)]
    for first in range(0, len(hosts), 10):  # ten hosts come and go between two scrapes
        status["links"] = [link(name, 1) for name in hosts[first:first + 10]]
        list(collector.collect())  # a scrape
    status["links"] = []
    found = samples(registry)
    assert len(found) <= MAX_LINK_LABELS + 1
    assert found[f'rosgate_link_frames_sent_total{{bridge="base",link="{OTHER_LINKS}"}}'] >= 49
