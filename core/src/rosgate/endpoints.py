"""The ROS endpoints of topic routes meet the graph's before data flows.

DDS pairs a new reader or writer with the remote ones its participant knows at once, while the
remote side learns of it only when its announcement arrives, and a volatile reader discards
what a writer sent before it learnt of that writer. Measured with Fast DDS: a subscriber made
while a publisher appears missed 5 to 8 of a publisher's first messages (the publisher had
matched it and published), and the first message of a publisher made next to a waiting
subscriber was lost in 1 of 6 tries (all of them while the participants were still finding each
other). So:

- a transmitting route subscribes once the graph shows a publisher of its topic (and it has
  somewhere to send): its reader pairs with every such writer as it is made, before any writer
  learns of it and publishes to it;
- a receiving route's publisher (at start, when a client (re)connects, when its QoS changes)
  holds what arrives until it has matched every subscription the graph shows for its topic and
  a moment has passed for those readers to learn of it (the graph showing none: only while
  the bridge's node is new and may not have found them yet); then it publishes what it holds,
  in order, and from then on the route publishes straight through it. The hold is bounded in time
  and count (:mod:`rosgate.matching`); what it cannot keep is counted ``not_matched``."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from .drops import Drop
from .matching import PACE_EACH, PublishGate
from .ros import RosNode
from .rostypes import QOS_UNFOUND, qos_profile
from .routes import ReceiveRoute, Route, TransmitRoute
from .warn import BUGS

#: seconds between looks at the graph for the first publisher of a topic nothing subscribes to yet
HEAR_EVERY = 0.05
#: seconds the looking thread sleeps while every transmitting route has its subscription
IDLE = 0.5


#: the least history the bridge's own subscription keeps for a reliable, volatile topic whose
#: QoS was found: a bridge that a busy machine stalls for a moment must not lose what its
#: publishers sent meanwhile (a volatile history is never replayed: only its bound changes)
RELAY_DEPTH = 100


def relay_profile(spec: int | str | dict) -> Any:
    """The profile of the bridge's own subscription for a QoS found from publishers: as found,
    but at least :data:`RELAY_DEPTH` deep when reliable, volatile and keep-last."""
    from rclpy import qos

    profile = qos_profile(spec)
    if (profile.reliability == qos.ReliabilityPolicy.RELIABLE
            and profile.durability == qos.DurabilityPolicy.VOLATILE
            and profile.history == qos.HistoryPolicy.KEEP_LAST):
        profile.depth = max(profile.depth, RELAY_DEPTH)
    return profile


class Endpoints:
    """Makes the subscriptions and publishers of a bridge's topic routes (under the router's
    ``lock``); ``announce(route)`` says a transmitting route's QoS once it found it."""

    def __init__(self, ros: RosNode, lock: threading.RLock,
                 announce: Callable[[TransmitRoute], None]):
        self.ros = ros
        self._lock = lock
        self._announce = announce
        #: transmitting routes that wait for a publisher to subscribe to
        self._unheard: set[TransmitRoute] = set()
        self._someone_unheard = threading.Event()
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._wait_for_publishers, name="hear",
                                        daemon=True)
        self._thread.start()

    # -- transmitting routes: a subscription once a publisher is there ----------------------
    def listen_when_heard(self, route: TransmitRoute) -> None:
        """Subscribe for ``route`` now if the graph shows a publisher, else as soon as it does."""
        with self._lock:
            self._unheard.add(route)
        if not self._hear(route):
            self._someone_unheard.set()

    def listen(self, route: TransmitRoute, qos: int | str | dict[str, Any]) -> None:
        profile = qos_profile(qos) if route.topic.qos_given else relay_profile(qos)
        route.entity = self.ros.subscribe(route.interface, route.topic.topic, profile,
                                          route.on_message, route.codec.raw,
                                          real_time=route.delivery.real_time)
        route.take = self.ros.taker(route.entity)

    def _hear(self, route: TransmitRoute) -> bool:
        """Subscribe for a waiting route if the graph shows a publisher of its topic (this
        bridge's own too: a server that relays) and it could send; whether it has a
        subscription now."""
        with self._lock:
            if route not in self._unheard:
                return True  # removed, or subscribed already
            if route.link.datagram and route.destination() is None:
                return False  # a server before the client's hello: it could send nothing
            if not self.ros.published(route.topic.topic):
                return False
            qos: int | str | dict[str, Any] = route.topic.qos
            if not route.topic.qos_given:
                route.qos_found = self.ros.qos_found(route.topic.topic)
                qos = route.qos_in_use = route.qos_found or QOS_UNFOUND
            self.listen(route, qos)
            self._unheard.discard(route)
        return True

    def _wait_for_publishers(self) -> None:
        """Every :data:`HEAR_EVERY` seconds while a transmitting route has no subscription,
        whether it may subscribe now."""
        while not self._closing.is_set():
            self._someone_unheard.wait(IDLE)
            with self._lock:
                unheard = list(self._unheard)
                if not unheard:
                    self._someone_unheard.clear()
            for route in unheard:
                try:
                    if self._hear(route) and route.announces and not route.topic.qos_given:
                        self._announce(route)  # the QoS it found
                except Exception:
                    BUGS.bug("hear_error", f"{route.label}: could not subscribe (a bug: please "
                                           "report it)")
            if self._closing.wait(HEAR_EVERY):
                return

    # -- receiving routes: a publisher behind a hold ------------------------------------------
    def publish(self, route: ReceiveRoute, qos: int | str | dict[str, Any]) -> None:
        """A receiving route's (new) publisher, behind a hold until it has matched the
        subscriptions the graph shows; a publisher it replaces hands its hold over."""
        profile = qos_profile(qos)
        publisher = self.ros.publisher(route.interface, route.topic.topic, profile)
        publish = (self.ros.raw_publisher(publisher) if route.codec.raw
                   else publisher.publish)

        def opened(publish: Callable[[Any], None]) -> None:
            with self._lock:
                if route.gate is gate:  # not replaced meanwhile
                    route.publish = publish

        gate = PublishGate(publish, lambda: self.ros.matched_all(publisher),
                           lambda why, count: _held_and_lost(route, why, count),
                           lambda exc: route.drop(Drop.PUBLISH_ERROR,
                                                  f"{type(exc).__name__}: {exc}"), opened,
                           lambda: self.ros.acknowledged(publisher, PACE_EACH),
                           self.ros.unacknowledged_at_most(profile))
        old, route.gate = route.gate, gate
        route.entity, route.publish = publisher, gate
        if old is not None:
            old.hand_over(gate)

    def forget(self, route: Route) -> None:
        """A route removed: it waits for no publisher, and what its publisher holds is lost."""
        with self._lock:
            if isinstance(route, TransmitRoute):
                self._unheard.discard(route)
        if isinstance(route, ReceiveRoute) and route.gate is not None:
            route.gate.close()

    def close(self) -> None:
        self._closing.set()
        self._someone_unheard.set()
        self._thread.join(timeout=2)


def _held_and_lost(route: ReceiveRoute, why: str, count: int) -> None:
    """Messages a new publisher held and could not keep."""
    detail = ("its new publisher's hold was full while it matched its subscribers"
              if why == "full" else "the route ended while its new publisher matched")
    for _ in range(count):
        route.drop(Drop.NOT_MATCHED, detail)
