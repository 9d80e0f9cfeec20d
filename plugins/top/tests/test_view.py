"""Rates from two statuses, and the view drawn from them (no terminal, no bridge)."""

from rich.console import Console
from rosgate_top.view import render, rows


def status(t: float, sent: int, drops: dict, up: bool = True) -> dict:
    return {"version": 1, "bridge": "robot1", "role": "client", "time": t, "uptime": t,
            "entries": [{"kind": "topic", "name": "/scan", "direction": "transmit",
                         "peer": "base", "type": "sensor_msgs/msg/LaserScan", "transport": "udp",
                         "port": None, "sent": sent, "bytes_sent": sent * 1000, "received": 0,
                         "bytes_received": 0, "lost": 0, "drops": drops, "queue": 3,
                         "stale": None, "silence": None, "latency": None, "refused": None},
                        {"kind": "service", "name": "/ping", "direction": "transmit",
                         "peer": "base", "type": "std_srvs/srv/Trigger", "transport": "tcp",
                         "port": None, "sent": 0, "bytes_sent": 0, "received": 0,
                         "bytes_received": 0, "lost": 0, "drops": {}, "queue": 0, "stale": None,
                         "silence": None, "latency": None, "refused": "not allowed by policy"}],
            "peers": [{"name": "base", "up": up}],
            "links": [{"name": "udp", "up": up, "frames_out": sent, "bytes_out": sent * 1000,
                       "packets_out": sent, "frames_in": 0, "bytes_in": 0, "packets_in": 0,
                       "queue": 3, "bandwidth": 8_000_000, "rtt": None}],
            "link_drops": {}}


def test_rates_are_differences_over_time():
    [scan, ping] = rows(status(12.0, 300, {"superseded": 5}), status(10.0, 100, {"superseded": 2}))
    assert scan.out_rate == 100.0 and scan.out_bytes == 100_000.0 and scan.in_rate == 0.0
    assert scan.new_drops == {"superseded": 3}
    assert ping.out_rate == 0.0
    [first, _] = rows(status(10.0, 100, {}), None)
    assert first.out_rate is None  # one status: no rate yet


def test_the_view_shows_rates_drops_refusals_and_budget():
    console = Console(width=200, record=True, color_system=None)
    console.print(render(status(12.0, 300, {"superseded": 5}, up=False),
                         status(10.0, 100, {"superseded": 2}), keys=False))
    text = console.export_text()
    scan = next(line for line in text.splitlines() if "/scan" in line)
    cells = [c.strip() for c in scan.split("│")[1:-1]]
    assert cells[:8] == ["/scan", "topic", "out", "base", "100", "0.0", "100.0 kB", "0 B"]
    assert cells[-3:] == ["3", "-", "superseded=5"]
    assert "refused: not allowed by policy" in text
    assert "peers: base DOWN" in text
    link = next(line for line in text.splitlines() if "│ udp" in line)
    assert "DOWN" in link and "10%" in link  # 800 kbit/s of an 8 Mbit/s budget


def test_a_topic_whose_queue_stands_behind_shows_it_sheds():
    console = Console(width=200, record=True, color_system=None)
    now = status(12.0, 300, {"too_late": 40})
    now["entries"][0]["shedding"] = True
    console.print(render(now, status(10.0, 100, {}), keys=False))
    scan = next(line for line in console.export_text().splitlines() if "/scan" in line)
    cells = [c.strip() for c in scan.split("│")[1:-1]]
    assert cells[-3:] == ["3 shedding", "-", "too_late=40"]
