"""Monitors export a running bridge's status (``/diagnostics``, Prometheus, any third party's):
a :class:`Monitor` subclass registered through the ``rosgate_monitors`` hook (docs/plugins.md,
"Monitors"), run when the file has its table under ``plugins:`` or its ``bridge:`` key.

The status is the plain, JSON-ready mapping ``rosgate top`` reads (:mod:`rosgate.status` describes
every field). Its counters only grow: rates are differences over the difference of ``time``.
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
