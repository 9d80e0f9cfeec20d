"""The ``diagnostics`` monitor: a ``diagnostic_msgs/msg/DiagnosticArray`` on
``/diagnostics`` once a second, as rqt_robot_monitor and diagnostic_aggregator read it.

One status per topic, service and link, and one per peer. Its ``name`` is
``rosgate: <bridge>: <entry>`` (``rosgate: robot1: topic /chatter (to base)``), its
``hardware_id`` the bridge's name, its ``values`` the counters (and ``pattern``, the pattern
entry that made the route, for a name a pattern found). The level:

* ERROR — the peer is down, or it refused the entry (its policy, a type it does not know);
* WARN — a receiving topic is stale, something was dropped since the last status, or a link
  sends more than its budget;
* OK — otherwise.

On for every bridge once installed; ``bridge.diagnostics: false`` turns it off.
``diagnostic_msgs`` is imported when the monitor starts, so a bridge without it only says so,
once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rosgate import Monitor, Status, hookimpl

log = logging.getLogger("rosgate")

TOPIC = "/diagnostics"
OK, WARN, ERROR = 0, 1, 2


class Diagnostics(Monitor):
    name = "diagnostics"

    @dataclass(frozen=True)
    class Options:
        """None: ``bridge.diagnostics`` turns it on or off."""

    def start(self) -> None:
        try:
            from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        except ImportError:
            log.warning("%s: no /diagnostics: the ROS package diagnostic_msgs is not installed "
                        "(install ros-<distro>-diagnostic-msgs, or set bridge.diagnostics: "
                        "false)", self.bridge.config.name)
            self.publisher = None
            return
        self.types = DiagnosticArray, DiagnosticStatus, KeyValue
        self.publisher = self.bridge.ros.publisher(DiagnosticArray, TOPIC, 10)
        self.before: Status | None = None

    def update(self, status: Status) -> None:
        if self.publisher is None:
            return
        array_type, status_type, key_value = self.types
        array = array_type()
        array.header.stamp = self.bridge.ros.node.get_clock().now().to_msg()
        for level, entry, message, values in assess(status, self.before):
            item = status_type(level=bytes([level]), name=f"rosgate: {status['bridge']}: {entry}",
                               message=message, hardware_id=status["bridge"])
            item.values = [key_value(key=k, value=str(v)) for k, v in values]
            array.status.append(item)
        self.before = status
        self.publisher.publish(array)

    def stop(self) -> None:
        self.publisher = None


def assess(now: Status, before: Status | None) -> list[tuple[int, str, str, list[tuple[str, Any]]]]:
    """(level, entry, message, values) for each topic, service, link and peer."""
    old = {_key(e): e for e in (before or {}).get("entries", [])}
    old_links = {link["name"]: link for link in (before or {}).get("links", [])}
    span = now["time"] - before["time"] if before else 0.0
    down = {str(p["name"]) for p in now["peers"] if p["up"] is False}
    out = []
    for e in now["entries"]:
        way = "to" if e["direction"] == "transmit" else "from"
        entry = f"{e['kind']} {e['name']} ({way} {e['peer']})"
        o = old.get(_key(e))
        dropped = {k: v - (o["drops"].get(k, 0) if o else 0) for k, v in e["drops"].items()}
        dropped = {k: v for k, v in dropped.items() if v > 0}
        if e["refused"] is not None:
            level, message = ERROR, f"refused by {e['peer']}: {e['refused']}"
        elif e["peer"] in down:
            level, message = ERROR, f"peer {e['peer']} is down"
        elif e["stale"]:
            level, message = WARN, f"stale: no message for {e['silence']:.0f} s"
        elif dropped:
            level, message = WARN, "dropped " + ", ".join(f"{k}={v}" for k, v in dropped.items())
        else:
            level, message = OK, "ok"
        values: list[tuple[str, Any]] = [(k, e[k]) for k in (
            "direction", "peer", "type", "transport", "sent", "bytes_sent", "received",
            "bytes_received", "lost", "queue")]
        if e.get("pattern"):  # the route a pattern entry made (a bridge older than it: none)
            values.append(("pattern", e["pattern"]))
        values += [(f"drops.{k}", v) for k, v in sorted(e["drops"].items())]
        if e["silence"] is not None:
            values.append(("silence", f"{e['silence']:.1f}"))
        out.append((level, entry, message, values))
    for link in now["links"]:
        o = old_links.get(link["name"])
        rate = (link["bytes_out"] - o["bytes_out"]) * 8 / span if o and span > 0 else 0.0
        if not link["up"]:
            level, message = ERROR, "down"
        elif link["bandwidth"] and rate > link["bandwidth"]:
            level, message = WARN, f"over budget: {rate:.0f} of {link['bandwidth']:.0f} bit/s"
        else:
            level, message = OK, "up"
        values = [(k, link[k]) for k in ("up", "frames_out", "bytes_out", "frames_in",
                                         "bytes_in", "queue", "bandwidth")]
        out.append((level, f"link {link['name']}", message, values))
    for p in now["peers"]:
        level = ERROR if p["up"] is False else OK
        out.append((level, f"peer {p['name']}", {True: "up", False: "down", None: "unknown"}[
            p["up"]], [("up", p["up"])]))
    return out


def _key(e: dict[str, Any]) -> tuple[Any, ...]:
    return e["kind"], e["name"], e["direction"], e["peer"]


@hookimpl
def rosgate_monitors(register: Callable[[type[Monitor]], None]) -> None:
    register(Diagnostics)
