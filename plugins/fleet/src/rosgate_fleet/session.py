"""What a bus transport of the ``fleet`` role provides: :class:`FleetTransport` (its keys) and
the :class:`BusSession` its ``open`` returns (publish, subscribe, queries, liveliness).

A bus moves whole frames by **key**: publish on a key, subscribe to a key expression
(``fleet/*/scan``) and receive each frame with the concrete key it was published on, serve and
issue queries (services), and declare and watch liveliness tokens (who is there). It discovers,
reconnects and fragments by itself, so rosgate does none of that on it: no length prefixes, no
fragments, no reconnection. rosgate keeps the envelope and the cipher (``framing: rosgate``) or
sends the codec's bytes bare (``framing: none``). An entry's ``remote`` is its key (default
:meth:`FleetTransport.default_key`).

Keys are ``/``-separated chunks without a leading or trailing ``/``; in a key expression ``*``
matches one chunk and ``**`` any number. Chunks that start with ``@`` are matched only by a
pattern that names them (``rosgate/*/@alive`` matches ``rosgate/robot1/@alive``; ``**`` does not).

Threads: the ``on_*`` callbacks a session is given may be called from the bus library's own
threads, several at once. rosgate's callbacks only queue what they get and return at once (a
slow callback can stall a bus library's whole session), so a plugin may call them from its
receive thread directly. A plugin must not leave threads that keep the process from exiting:
:meth:`BusSession.close` ends everything it started.
"""

from __future__ import annotations

import re
from abc import abstractmethod
from collections.abc import Callable
from typing import Any, Protocol

from rosgate import BusTransport, ServiceConfig, TopicConfig

_CHUNK = re.compile(r"[^/*$?#]+|\*|\*\*")


class Handle(Protocol):
    """A declaration (subscription, queryable, token, watch); ``close`` withdraws it."""

    def close(self) -> None: ...


class BusPublisher(Protocol):
    """Publishes on one key."""

    def put(self, frame: bytes) -> None:
        """Hand one frame to the bus. Raise ``OSError`` when it cannot be handed over (counted
        as ``send_error``). A reliable publisher may wait while the bus is congested; a
        best-effort one drops instead, silently, as the bus does."""

    def close(self) -> None: ...


class BusQuery(Protocol):
    """One query received by a queryable: answer it once, or close it without an answer."""

    def reply(self, payload: bytes) -> None:
        """Answer with ``payload``; raise ``OSError`` when the answer cannot be sent."""

    def close(self) -> None:
        """Finish the query (after a reply, or instead of one: the caller then gets none)."""


#: a frame arrived: (the concrete key it was published on, the frame)
SampleHandler = Callable[[str, bytes], None]
#: a query arrived: (the concrete key, its payload, the query to answer)
QueryHandler = Callable[[str, bytes, BusQuery], None]
#: liveliness: (a token's key, True when it appeared, False when it went)
ChangeHandler = Callable[[str, bool], None]


class BusSession(Protocol):
    """An open session on the bus. Every method but ``close`` may be called from any thread."""

    def publisher(self, key: str, *, reliable: bool, priority: int) -> BusPublisher:
        """A publisher on ``key``. ``reliable``: the topic's QoS is reliable, so the bus should
        push back when congested rather than drop (zenoh: ``CongestionControl.BLOCK``), else
        drop (``DROP``). ``priority``: 1 (real time) to 7 (background), as
        :data:`rosgate.config.PRIORITIES`."""

    def subscribe(self, key_expr: str, on_sample: SampleHandler) -> Handle:
        """Deliver every frame published on a key matching ``key_expr`` to ``on_sample``."""

    def serve(self, key: str, on_query: QueryHandler) -> Handle:
        """Answer queries on ``key``: each is handed to ``on_query`` with a :class:`BusQuery`."""

    def query(self, key: str, payload: bytes, timeout: float,
              on_reply: Callable[[bytes], None], on_done: Callable[[int], None]) -> None:
        """Send one query and return at once. ``on_reply(payload)`` for each answer;
        ``on_done(answers)`` once when the query is over (all servers answered, none serves the
        key, or ``timeout`` seconds passed). Raise ``OSError`` when it cannot be sent."""

    def token(self, key: str) -> Handle:
        """Declare a liveliness token on ``key``, held until closed or the session ends."""

    def watch(self, key_expr: str, on_change: ChangeHandler) -> Handle:
        """Report tokens matching ``key_expr``: those already declared at once (``True``), then
        each that appears (``True``) or goes (``False``: withdrawn, or its holder is gone)."""

    def close(self) -> None:
        """Close the session and everything declared on it, promptly."""


class NameTemplates(Protocol):
    """Entries whose names hold placeholders (``topic: /{robot}/scan`` with ``remote:
    fleet/{robot}/scan``): one entry in the file, a route for each value the bus finds. A bus that
    takes them sets :attr:`FleetTransport.templates`; the zenoh plugin's fleets are the example."""

    def check(self, entry: TopicConfig | ServiceConfig, key: str) -> None:
        """Refuse a templated entry whose key is ``key`` (its ``remote``, or the default key)
        with a :class:`rosgate.ConfigError` whose ``key`` is the entry's field (``remote``)."""

    def start(self, wiring: Any, link: Any) -> Callable[[Any], None]:
        """Begin on one bus link of a bridge (a :class:`rosgate_fleet.BusWiring` and its
        :class:`rosgate_fleet.BusLink`); the function returned takes each templated entry of
        that link (a prepared topic or service) as the bridge starts."""


class Dialect(Protocol):
    """Entries a bus wires in another system's convention rather than rosgate's own (the zenoh
    plugin: zenoh-bridge-ros2dds's and rmw_zenoh's graph announcements, history and bare service
    calls). A bus that has one sets :attr:`FleetTransport.dialect`."""

    def name(self, entry: TopicConfig | ServiceConfig) -> str | None:
        """The convention ``entry`` follows, in a few words for ``rosgate check``; None:
        wired as rosgate's own."""

    def check(self, entry: TopicConfig | ServiceConfig, key: str) -> None:
        """Refuse an entry (whose :meth:`name` is not None) that the convention cannot carry,
        with a :class:`rosgate.ConfigError` whose ``key`` is the entry's field."""

    def wire(self, wiring: Any, link: Any, entry: Any) -> None:
        """Make the routes of one prepared entry (a topic or a service) on one bus link of a
        bridge (a :class:`rosgate_fleet.BusWiring` and its :class:`rosgate_fleet.BusLink`),
        with the wiring's methods and the link's session."""

    def publishers(self, wiring: Any, link: Any,
                   listener: Callable[[str, str, bool], None]) -> None:
        """Call ``listener(name, type, alive)`` on the link's thread for each topic publisher
        the convention announces on ``link`` (another system's graph), now and as they come
        (``alive``) and go: its ROS name as an entry of this bridge would carry it without
        ``remote``, and its ROS type (``pkg/msg/Type``). What a peer's receiving pattern
        entries find (:meth:`rosgate.BusRole.pattern`)."""


def is_template(text: str) -> bool:
    """Whether an entry's name or key holds a placeholder (``{robot}``)."""
    return "{" in text or "}" in text


class FleetTransport(BusTransport):
    """Base class of the bus transports the ``fleet`` role wires. Set :attr:`name`; implement
    :meth:`open`, returning a :class:`BusSession`. Set :attr:`prefix` from your options if you
    take it."""

    #: rosgate's own keys start with it: ``<prefix>/<bridge name>/<topic>`` and the liveliness
    #: token ``<prefix>/<bridge name>/@alive``
    prefix: str = "rosgate"
    #: entries with placeholders, or None: this bus takes none
    templates: NameTemplates | None = None
    #: entries wired in another system's convention, or None: every entry is rosgate's
    dialect: Dialect | None = None

    @abstractmethod
    def open(self, name: str) -> BusSession:
        """Open a session for the bridge called ``name``. Raise :class:`rosgate.LinkError` when it
        cannot be opened (no router where one is required, a port in use)."""

    def check_key(self, key: str) -> str:
        """Validate a key (or key expression) written in bringup.yaml; ``ValueError`` with a
        sentence saying what is wrong. The default checks the chunk rules above."""
        return check_key(key)

    def default_key(self, bridge: str, ros_name: str, bare: bool) -> str:
        """The key of an entry without ``remote``: the ROS name without its slash for bare
        frames, else ``<prefix>/<bridge>/<name>``."""
        name = ros_name.removeprefix("/")
        return name if bare else f"{self.prefix}/{bridge}/{name}"

    def alive_key(self, bridge: str) -> str:
        """The liveliness token a bridge declares for itself."""
        return f"{self.prefix}/{bridge}/@alive"


def check_key(key: str) -> str:
    """The chunk rules of keys (module docstring); ``ValueError`` saying which is broken."""
    if not key or key.startswith("/") or key.endswith("/"):
        raise ValueError(f"{key!r} is not a key: no leading or trailing '/', not empty")
    for chunk in key.split("/"):
        if not _CHUNK.fullmatch(chunk):
            raise ValueError(f"{key!r} is not a key: chunk {chunk!r} is empty or holds "
                             "'*', '$', '?' or '#' (a wildcard is '*' or '**' alone)")
    return key
