"""rosgate transport ``zenoh``: an Eclipse Zenoh bus, for fleets.

A bus link (:mod:`rosgate.bus`): topics are published on keys, services are queryables, and each
bridge holds a liveliness token. Zenoh routes, fragments, discovers and reconnects; rosgate
keeps its envelope and cipher (``framing: rosgate``) or sends the codec's bytes bare
(``framing: none``, the zenoh-bridge-ros2dds convention with ``codec: cdr``).

Options (``plugins: {zenoh: {...}}``): two are rosgate's —

* ``prefix`` (default ``rosgate``): the first part of rosgate's own keys,
  ``<prefix>/<bridge name>/<topic>``, and of its liveliness tokens ``<prefix>/<name>/@alive``.
  Every bridge of a fleet uses the same prefix.
* ``namespace`` (default ``/``, none): the key of a ``framing: none`` entry without ``remote`` is
  ``<namespace>/<ROS name>``, as zenoh-bridge-ros2dds' ``namespace`` option makes it.

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

Threads: zenoh calls rosgate directly from its own receive threads (``Callback(...,
indirect=False)``): rosgate only queues there, and no Python thread is left behind to keep a
process from exiting. Sessions are closed explicitly when the bridge stops.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from rosgate import LinkError, OptionError, hookimpl
from rosgate.bus import BusTransport

log = logging.getLogger("rosgate.zenoh")

OWN_OPTIONS = ("prefix", "namespace")
_PRIORITIES = (zenoh.Priority.REAL_TIME, zenoh.Priority.INTERACTIVE_HIGH,
               zenoh.Priority.INTERACTIVE_LOW, zenoh.Priority.DATA_HIGH, zenoh.Priority.DATA,
               zenoh.Priority.DATA_LOW, zenoh.Priority.BACKGROUND)
_NO_CONSOLIDATION = zenoh.ConsolidationMode.NONE  # every answer, not the "best" one
_FIX = "see zenoh's DEFAULT_CONFIG.json5 for the options and their forms"


def zenoh_message(exc: BaseException) -> str:
    """A ZError in words: without the Rust source location, serde's message unwrapped."""
    text = str(exc).split(" at /", 1)[0].strip()
    found = re.search(r'msg: "((?:[^"\\]|\\.)*)"', text)
    if found:
        return found.group(1).replace('\\"', '"')
    return "unknown option" if text == 'Str("unknown key")' else text


def zenoh_config(options: Mapping[str, Any]) -> zenoh.Config:
    """The zenoh part of the options as a ``zenoh.Config``; :class:`OptionError` naming the
    option (its dotted path) for anything zenoh refuses."""
    given = {k: v for k, v in options.items() if k not in OWN_OPTIONS}
    for key in ("connect", "listen"):
        if isinstance(given.get(key), list):
            given[key] = {"endpoints": given[key]}
    scouting = given.setdefault("scouting", {})
    if isinstance(scouting, dict):
        multicast = scouting.setdefault("multicast", {})
        if isinstance(multicast, dict):
            multicast.setdefault("enabled", False)
    config = zenoh.Config()
    for key, value in given.items():
        _insert(config, key, value)
    return config


def _insert(config: zenoh.Config, path: str, value: Any) -> None:
    try:
        config.insert_json5(path, json.dumps(value))
    except zenoh.ZError as exc:
        if isinstance(value, dict) and value:  # name the option inside that is wrong
            for key, inner in value.items():
                _insert(config, f"{path}/{key}", inner)
        message = zenoh_message(exc)
        if message == "unknown option":
            parent, _, last = path.rpartition("/")
            message = f"unknown zenoh option '{last}'" + (f" under {parent.replace('/', '.')}"
                                                          if parent else "")
        raise OptionError(path.replace("/", "."), message, _FIX) from None
    except (TypeError, ValueError) as exc:  # a value json cannot write: YAML gave something odd
        raise OptionError(path.replace("/", "."), f"cannot be passed to zenoh: {exc}",
                          _FIX) from None


class ZenohTransport(BusTransport):
    name = "zenoh"

    def __init__(self, options: Mapping[str, Any]):
        super().__init__(options)
        prefix = self.options.get("prefix", "rosgate")
        if not isinstance(prefix, str):
            raise OptionError("prefix", f"expected text, got {prefix!r}", "e.g. prefix: fleet")
        try:
            self.prefix = self.check_key(prefix)
        except ValueError as exc:
            raise OptionError("prefix", str(exc), "e.g. prefix: fleet") from None
        namespace = self.options.get("namespace", "/")
        fix = "e.g. namespace: /bot1 (as zenoh-bridge-ros2dds writes it)"
        if not isinstance(namespace, str):
            raise OptionError("namespace", f"expected a ROS namespace, got {namespace!r}", fix)
        self.namespace = namespace.strip("/")
        if self.namespace:
            try:
                self.check_key(self.namespace)
            except ValueError as exc:
                raise OptionError("namespace", str(exc), fix) from None
        zenoh_config(self.options)  # refuse wrong options now: `rosgate check` shows them

    def check_key(self, key: str) -> str:
        super().check_key(key)
        try:
            zenoh.KeyExpr(key)
        except zenoh.ZError as exc:
            raise ValueError(f"{key!r} is not a zenoh key expression: "
                             f"{zenoh_message(exc)}") from None
        return key

    def open(self, name: str) -> ZenohSession:
        try:
            session = zenoh.open(zenoh_config(self.options))
        except zenoh.ZError as exc:
            raise LinkError(f"zenoh: cannot open a session: {zenoh_message(exc)}",
                            "check plugins.zenoh: with mode: client a router must answer at one "
                            "of connect.endpoints; mode: peer opens without one") from None
        info = session.info
        log.info("%s: zenoh session %s (%s), routers %s", name, session.zid(),
                 self.options.get("mode", "peer"), [str(z) for z in info.routers_zid()] or "none")
        return ZenohSession(session)

    def router(self, listen: list[str], config_file: str | None) -> ZenohSession:
        try:
            config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
            config.insert_json5("mode", json.dumps("router"))
            if listen:
                config.insert_json5("listen/endpoints", json.dumps(listen))
            if not config_file:
                config.insert_json5("scouting/multicast/enabled", "false")
            return ZenohSession(zenoh.open(config))
        except zenoh.ZError as exc:
            raise LinkError(f"zenoh router: {zenoh_message(exc)}", "check --listen "
                            "(tcp/<address>:<port>, the port free) and --config") from None


class _Declared:
    """A subscription, queryable, token or watch: ``close`` undeclares it."""

    def __init__(self, entity: Any, forget: Callable[[], None] | None = None):
        self.entity = entity
        self.forget = forget

    def close(self) -> None:
        if self.forget is not None:
            self.forget()
        try:
            self.entity.undeclare()
        except zenoh.ZError:  # already gone with its session
            pass


class _Publisher:
    def __init__(self, publisher: zenoh.Publisher):
        self.publisher = publisher

    def put(self, frame: bytes) -> None:
        try:
            self.publisher.put(frame)
        except zenoh.ZError as exc:
            raise OSError(zenoh_message(exc)) from None

    def close(self) -> None:
        try:
            self.publisher.undeclare()
        except zenoh.ZError:
            pass


class _Query:
    """A query received: answered on the queryable's own key (zenoh requires a key that
    intersects the query's), then dropped, which tells the caller it is over."""

    def __init__(self, query: zenoh.Query, key: str):
        self.query = query
        self.key = key

    def reply(self, payload: bytes) -> None:
        try:
            self.query.reply(self.key, payload)
        except zenoh.ZError as exc:
            raise OSError(zenoh_message(exc)) from None

    def close(self) -> None:
        try:
            self.query.drop()
        except zenoh.ZError:
            pass


def _direct(callback: Callable[[Any], None], drop: Callable[[], None] | None = None) -> Any:
    """Run ``callback`` on zenoh's receive thread: no Python thread per declaration (zenoh's
    default handler makes non-daemon ones, which hang a process that exits without closing)."""
    return zenoh.handlers.Callback(callback, drop, indirect=False)


class ZenohSession:
    """A :class:`rosgate.bus.BusSession` over one ``zenoh.Session``."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        # zenoh undeclares a token whose last reference goes; the bus contract holds it until
        # it is closed, so the session keeps it
        self._tokens: set[_Declared] = set()

    def publisher(self, key: str, *, reliable: bool, priority: int) -> _Publisher:
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        return _Publisher(self.session.declare_publisher(
            key, congestion_control=congestion, priority=_PRIORITIES[priority - 1]))

    def subscribe(self, key_expr: str, on_sample: Callable[[str, bytes], None]) -> _Declared:
        return _Declared(self.session.declare_subscriber(key_expr, _direct(
            lambda sample: on_sample(str(sample.key_expr), sample.payload.to_bytes()))))

    def serve(self, key: str, on_query: Callable[[str, bytes, Any], None]) -> _Declared:
        def arrived(query: zenoh.Query) -> None:
            payload = query.payload
            on_query(str(query.key_expr), payload.to_bytes() if payload is not None else b"",
                     _Query(query, key))

        return _Declared(self.session.declare_queryable(key, _direct(arrived)))

    def query(self, key: str, payload: bytes, timeout: float,
              on_reply: Callable[[bytes], None], on_done: Callable[[int], None]) -> None:
        answers = [0]

        def reply(got: zenoh.Reply) -> None:
            if got.ok is not None:
                answers[0] += 1
                on_reply(got.ok.payload.to_bytes())
            else:  # zenoh's own "Timeout", or a server's reply_err: no answer
                log.debug("zenoh: query on %s: %s", key,
                          got.err.payload.to_bytes()[:200] if got.err is not None else "?")

        try:
            self.session.get(key, _direct(reply, lambda: on_done(answers[0])), payload=payload,
                             timeout=timeout, consolidation=_NO_CONSOLIDATION)
        except zenoh.ZError as exc:
            raise OSError(zenoh_message(exc)) from None

    def token(self, key: str) -> _Declared:
        token = _Declared(self.session.liveliness().declare_token(key),
                          lambda: self._tokens.discard(token))
        self._tokens.add(token)
        return token

    def watch(self, key_expr: str, on_change: Callable[[str, bool], None]) -> _Declared:
        put = zenoh.SampleKind.PUT
        return _Declared(self.session.liveliness().declare_subscriber(
            key_expr, _direct(lambda sample: on_change(str(sample.key_expr), sample.kind == put)),
            history=True))

    def close(self) -> None:
        self.session.close()
        self._tokens.clear()


@hookimpl
def rosgate_transports(register: Any) -> None:
    register(ZenohTransport)
