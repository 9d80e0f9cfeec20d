"""Monitors: what watches a running bridge and tells the world — ``/diagnostics``
(``rosgate-diagnostics``), a Prometheus endpoint (``rosgate-metrics-prometheus``), or any
exporter a third party writes: a :class:`Monitor` subclass registered through the
``rosgate_monitors`` hook (an example: docs/plugins.md, "Monitors").

A monitor runs when the bridge's file asks for it: by its table under ``plugins:``
(``plugins: {statsd: {address: ...}}``, parsed against its ``Options``), or by a ``bridge:`` key
rosgate knows (``diagnostics``, on unless ``false``; ``metrics: host:port``). It reads the
bridge only through its **status**: a plain, JSON-ready mapping, the same one ``rosgate top``
reads from the bridge's local socket (:mod:`rosgate.status` describes every field). Counters in
it only grow; a monitor that wants rates keeps the previous status and divides by the difference
of their ``time``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from .config import BridgeConfig

Status = dict[str, Any]


@dataclass(frozen=True)
class Watched:
    """What a monitor is given of the bridge it watches."""

    #: the bridge's file, as loaded
    config: BridgeConfig
    #: the status now (cheap: counters are read, nothing on the data path waits)
    status: Callable[[], Status]
    #: the bridge's ROS node (:class:`rosgate.ros.RosNode`): ``publisher(type, topic, qos)``
    ros: Any
    #: set when the bridge stops
    stopping: threading.Event


class Monitor:
    """One exporter of a bridge's status. Subclasses set :attr:`name`, may declare ``Options``
    (a frozen dataclass, as transports do) and override what they need."""

    name: ClassVar[str]

    def __init__(self, bridge: Watched, options: Any):
        self.bridge = bridge
        self.options = options  # the parsed Options of plugins: <name>: ({} without Options)

    def start(self) -> None:
        """Called once the bridge runs. Raise :class:`rosgate.ConfigError` (with
        ``bridge.config.error(key, ...)``) for a setting that cannot work: the bridge stops."""

    def update(self, status: Status) -> None:
        """Called about once a second from the bridge's housekeeping thread with a fresh status.
        Return quickly: the next stale warning and summary line wait for it."""

    def stop(self) -> None:
        """Called when the bridge stops; release what :meth:`start` took."""
