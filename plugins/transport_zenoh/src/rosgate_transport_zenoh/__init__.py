"""rosgate transport ``zenoh``: an Eclipse Zenoh bus, for fleets.

A bus link (:mod:`rosgate_fleet`): topics are published on keys, services are queryables, and each
bridge holds a liveliness token. Zenoh routes, fragments, discovers and reconnects; rosgate
keeps its envelope and cipher (``framing: rosgate``) or sends the codec's bytes bare
(``framing: none``, the zenoh-bridge-ros2dds convention with ``codec: cdr``).

Options (``plugins: {zenoh: {...}}``): five are rosgate's —

* ``prefix`` (default ``rosgate``): the first part of rosgate's own keys,
  ``<prefix>/<bridge name>/<topic>``, and of its liveliness tokens ``<prefix>/<name>/@alive``.
  Every bridge of a fleet uses the same prefix.
* ``namespace`` (default ``/``, none): the key of a ``framing: none`` entry without ``remote`` is
  ``<namespace>/<ROS name>``, as zenoh-bridge-ros2dds' ``namespace`` option makes it.
* ``speak`` (default ``rosgate``): ``ros2dds`` wires bare-CDR entries as zenoh-bridge-ros2dds
  does — liveliness tokens, publication caches, raw service calls (:mod:`.dialect`);
  ``rmw_zenoh`` wires bare-CDR topics as a node running rmw_zenoh does — its keys, attachments
  and graph tokens (:mod:`.rmw_dialect`), in the ROS domain ``domain`` (default: the bridge's).
* ``tls``: a folder made by ``rosgate certs``: zenoh's mutual TLS with the fleet's CA
  (:mod:`.tls`). An entry that takes frames from the bus (a receiving topic, a service, an
  action) without a keyed cipher needs it, with ``tls/`` endpoints alone, no listener of zenoh's
  default (``mode: client``, or ``listen:`` said) and no multicast scouting
  (:meth:`ZenohTransport.unauthenticated`); else the file says ``bridge.insecure: true``.

— and everything else is zenoh's own configuration, passed through as written (its
``DEFAULT_CONFIG.json5``): ``mode: peer|client``, ``connect: {endpoints: [...]}``,
``listen: {endpoints: [...]}``, ``transport: {link: {tls: {...}}}``, ... A list for ``connect``
or ``listen`` is taken as its ``endpoints``. Unless the file says otherwise, multicast scouting is
off (so nothing is found, or announced, that ``connect`` and ``listen`` do not name). A wrong
option is an error at its line, in zenoh's words.

Mapping: a topic with reliable QoS publishes with ``CongestionControl.BLOCK`` (zenoh holds the
publisher while the link is congested, up to its ``wait_before_close``), best effort with
``DROP``; ``priority:`` 1..7 is zenoh's ``Priority`` (``REAL_TIME`` .. ``BACKGROUND``, default
``DATA``). A service call is one ``get`` (consolidation ``NONE``, its first answer wins).

Fleets (:mod:`.fleet`): an entry may name its robot by placeholder, ``topic: /{robot}/scan``
with ``remote: fleet/{robot}/scan`` (:mod:`.placeholders`): one wildcard subscription, a route
per robot found by its frames or its liveliness token. ``rosgate router`` (:mod:`.router`) runs
a zenoh router for bridges to meet at (with ``--tls``, mutual TLS and per-robot access control);
``rosgate certs`` makes the fleet's certificates.

Threads: zenoh calls rosgate directly from its own receive threads (``Callback(...,
indirect=False)``): rosgate only queues there, and no Python thread is left behind to keep a
process from exiting. Sessions are closed explicitly when the bridge stops.
"""

from __future__ import annotations

from typing import Any

from rosgate import hookimpl

from .router import CERTS, ROUTER
from .session import ZenohSession, zenoh_message
from .transport import ZenohTransport, zenoh_config

__all__ = ["ZenohSession", "ZenohTransport", "zenoh_config", "zenoh_message"]


@hookimpl
def rosgate_transports(register: Any) -> None:
    register(ZenohTransport)


@hookimpl
def rosgate_commands(register: Any) -> None:
    register(ROUTER)
    register(CERTS)
