"""The ``metrics`` monitor: a bridge's counters on a Prometheus endpoint.

``bridge.metrics: host:port`` turns it on. It binds loopback only unless ``bridge.metrics_public:
true`` says otherwise: the counters name every topic and peer. Each scrape reads the bridge's
status once (:mod:`rosgate.status`) and turns it into labelled families; nothing is kept
between scrapes, so what Prometheus sees is what the bridge counted.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Callable
from dataclasses import dataclass
from importlib.util import find_spec

from rosgate import Monitor, hookimpl, parse_host_port

# prometheus_client takes a while to import: the monitor imports it (and .families) when it
# starts, not when the plugin loads; missing, it still makes the plugin fail to load, by name
if find_spec("prometheus_client") is None:
    raise ModuleNotFoundError("No module named 'prometheus_client'", name="prometheus_client")


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: it may resolve anywhere


class Metrics(Monitor):
    name = "metrics"

    @dataclass(frozen=True)
    class Options:
        """None: ``bridge.metrics`` and ``bridge.metrics_public`` say where to serve."""

    def start(self) -> None:
        cfg = self.bridge.config
        assert cfg.metrics is not None
        try:
            host, port = parse_host_port(cfg.metrics)
        except ValueError as exc:
            raise cfg.error("bridge.metrics", str(exc), "e.g. metrics: 127.0.0.1:9108") from None
        if not is_loopback(host) and not cfg.metrics_public:
            raise cfg.error("bridge.metrics", f"{host} is not a loopback address: anyone who "
                            "reaches it would read every topic and peer name and count",
                            "serve on 127.0.0.1 (and scrape through a tunnel or a local agent), "
                            "or add metrics_public: true to bridge:")
        from prometheus_client import CollectorRegistry, start_http_server

        from .families import StatusCollector

        registry = CollectorRegistry(auto_describe=False)
        registry.register(StatusCollector(self.bridge.status))
        try:
            self.server, _ = start_http_server(port, host, registry=registry)
        except OSError as exc:
            raise cfg.error("bridge.metrics", f"cannot serve metrics on {cfg.metrics}: "
                            f"{exc.strerror or exc}", "pick a free port") from None

    def stop(self) -> None:
        server = getattr(self, "server", None)
        if server is not None:
            server.shutdown()
            server.server_close()


@hookimpl
def rosgate_monitors(register: Callable[[type[Monitor]], None]) -> None:
    register(Metrics)
