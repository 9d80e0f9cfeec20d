"""The far graph, mirrored honestly (client/server; docs/services.md): a service bridged across
has its proxy on the calling side only while a real ROS server of it runs on the serving side.
The serving side looks at its graph with the router's watch (every 0.5 s) for servers outside
rosgate's namespace and says what it found, in its hello or welcome item and its announcements
(``served``, :mod:`rosgate.announce`); the calling side makes its proxy when told one runs and
takes it down when told none does."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from .ros import RosNode
from .routes import Route
from .services import CallerRoute, ServerRoute, deep_qos
from .warn import BUGS

log = logging.getLogger("rosgate")


class Proxies:
    """The proxies of a router's mirrored services. ``lock`` is the router's (a route removed
    under it gets no proxy after), ``announce`` says a route's entry on its link, ``live``
    whether a route is still the router's."""

    def __init__(self, ros: RosNode, lock: threading.RLock, announce: Callable[[Route], None],
                 live: Callable[[Route], bool]):
        self.ros, self._lock, self.announce, self.live = ros, lock, announce, live

    def make(self, route: CallerRoute) -> Any:
        """The ROS service of a calling route: its calls cross the link."""
        return self.ros.deferred_service(route.srv_type, route.service.service, deep_qos(),
                                         route.on_request)

    def follow(self, route: CallerRoute) -> None:
        """What the far side said of its server: a mirrored proxy appears when one runs there
        and goes when none does (calls waiting on it are answered by their deadlines)."""
        if not route.mirrored:
            return
        gone = None
        with self._lock:
            if not self.live(route):
                return  # removed meanwhile
            if route.far_served and route.entity is None:
                route.entity = self.make(route)
                log.info("%s: a server runs on the far side: its proxy is here", route.label)
            elif not route.far_served and route.entity is not None:
                gone, route.entity = route.entity, None
        if gone is not None:
            self.ros.destroy(gone)
            log.info("%s: no server runs on the far side: its proxy is gone", route.label)

    def watch(self, routes: list[Route]) -> None:
        """Whether a real ROS server runs here for each mirrored service this side serves: a
        change is said to the far side at once (and with every announcement after)."""
        serving = [r for r in routes if isinstance(r, ServerRoute) and r.mirror]
        if not serving:
            return
        try:
            served = self.ros.served({r.service.service for r in serving})
        except Exception:  # a graph query that failed (shutting down): the next look retries
            log.debug("could not look for the servers of served services", exc_info=True)
            return
        try:
            self._tell(serving, served)
        except Exception:  # the router's watch goes on with its other routes
            BUGS.bug("announce_error", "could not say whether served services have their "
                                       "servers (a bug: please report it)")

    def _tell(self, serving: list[ServerRoute], served: set[str]) -> None:
        for route in serving:
            now = route.service.service in served
            if now == route.served or not self.live(route):
                continue
            route.served = now
            log.info("%s: %s", route.label, "a server runs here: the far side's proxy appears"
                     if now else "its server here is gone: the far side's proxy goes")
            if route.announces:
                self.announce(route)
