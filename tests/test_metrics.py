"""The Prometheus endpoint (rosgate-metrics-prometheus): a scrape shows the bridge's counters as
labelled families; a non-loopback address is refused unless the file says so."""

from __future__ import annotations

import re
import urllib.request

import pytest
from conftest import free_port, wait_until
from prometheus_client.parser import text_string_to_metric_families
from std_msgs.msg import String
from test_status import Publisher

from rosgate.errors import ConfigError


def scrape(port: int) -> dict[str, float]:
    """Each sample as ``name{label="value",...}`` with its labels sorted, and its value."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as answer:
        assert answer.status == 200
        text = answer.read().decode()
    samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            labels = ",".join(f'{k}="{v}"' for k, v in sorted(s.labels.items()))
            samples[f"{s.name}{{{labels}}}"] = s.value
    return samples


def test_a_scrape_shows_the_counters(engines, domain, ros_side):
    port, metrics = free_port(), free_port()
    ds, dc = domain(), domain()
    engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, metrics: '127.0.0.1:{metrics}'}}
topics:
  - {{topic: /flow, type: std_msgs/msg/String, direction: transmit, max_rate: 10}}
""", dc)
    assert [m.name for m in client.monitors] == ["diagnostics", "metrics"]
    listener = ros_side(ds, "base").listen("/flow", String)
    publisher = Publisher(ros_side(dc, "robot"), 50)
    try:
        assert listener.wait_count(5, 20)
        assert wait_until(lambda: client.status()["entries"][0]["drops"].get("rate_limit", 0) > 5)
    finally:
        publisher.close()
    flow = client.status()["entries"][0]
    samples = scrape(metrics)
    labels = 'bridge="robot1",direction="transmit",kind="topic",peer="base",topic="/flow"'
    sent = samples[f"rosgate_messages_sent_total{{{labels}}}"]
    assert sent >= flow["sent"] > 0  # the scrape came after the status: counters only grow
    assert samples[f"rosgate_bytes_sent_total{{{labels}}}"] >= sent * 3
    with_reason = labels.replace(",topic", ',reason="rate_limit",topic')
    dropped = samples[f"rosgate_drops_total{{{with_reason}}}"]
    assert dropped >= flow["drops"]["rate_limit"] > 5
    assert samples['rosgate_peer_up{bridge="robot1",peer="base"}'] == 1.0
    links = {k: v for k, v in samples.items() if k.startswith("rosgate_link_up{")}
    assert links and all(re.fullmatch(r'rosgate_link_up\{bridge="robot1",link=".+"\}', k)
                         for k in links)
    assert samples['rosgate_uptime_seconds{bridge="robot1"}'] > 0


def test_a_public_address_is_refused_unless_asked(engines, domain):
    port = free_port()
    with pytest.raises(ConfigError) as caught:
        engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, "
                f"metrics: '0.0.0.0:{free_port()}'}}", domain())
    message = str(caught.value)
    assert "bridge.metrics" in message and "0.0.0.0 is not a loopback address" in message
    assert "metrics_public: true" in message


def test_the_endpoint_is_gone_when_the_bridge_stops(engines, domain):
    metrics = free_port()
    server = engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{free_port()}, "
                     f"metrics: 'localhost:{metrics}'}}", domain())
    assert scrape(metrics)['rosgate_uptime_seconds{bridge="base"}'] >= 0
    server.stop()
    with pytest.raises(OSError):
        scrape(metrics)
