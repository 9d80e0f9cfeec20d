"""A bus session over one ``zenoh.Session`` (:class:`rosgate_fleet.BusSession`): publishers,
subscriptions, queryables, queries and liveliness tokens, for both dialects (the rmw_zenoh one
subclasses it) and for the router."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

log = logging.getLogger("rosgate.zenoh")

PRIORITIES = (zenoh.Priority.REAL_TIME, zenoh.Priority.INTERACTIVE_HIGH,
              zenoh.Priority.INTERACTIVE_LOW, zenoh.Priority.DATA_HIGH, zenoh.Priority.DATA,
              zenoh.Priority.DATA_LOW, zenoh.Priority.BACKGROUND)
NO_CONSOLIDATION = zenoh.ConsolidationMode.NONE  # every answer, not the "best" one


def zenoh_message(exc: BaseException) -> str:
    """A ZError in words: without the Rust source location, serde's message unwrapped."""
    text = str(exc).split(" at /", 1)[0].strip()
    found = re.search(r'msg: "((?:[^"\\]|\\.)*)"', text)
    if found:
        return found.group(1).replace('\\"', '"')
    return "unknown option" if text == 'Str("unknown key")' else text


class Declared:
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


class ZenohPublisher:
    def __init__(self, publisher: zenoh.Publisher | zenoh.ext.AdvancedPublisher):
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


class ZenohQuery:
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


def direct(callback: Callable[[Any], None], drop: Callable[[], None] | None = None) -> Any:
    """Run ``callback`` on zenoh's receive thread: no Python thread per declaration (zenoh's
    default handler makes non-daemon ones, which hang a process that exits without closing)."""
    return zenoh.handlers.Callback(callback, drop, indirect=False)


class ZenohSession:
    """A :class:`rosgate_fleet.BusSession` over one ``zenoh.Session``."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        # zenoh undeclares a token whose last reference goes; the bus contract holds it until
        # it is closed, so the session keeps it
        self._tokens: set[Declared] = set()

    def zid(self) -> str:
        """This session's zenoh id, as keys write it."""
        return str(self.session.zid())

    def publisher(self, key: str, *, reliable: bool, priority: int,
                  history: int = 0) -> ZenohPublisher:
        """``history``: keep that many last samples for late joiners to query (zenoh-ext's
        advanced publisher with a cache and publisher detection, as zenoh-bridge-ros2dds
        serves transient_local topics)."""
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        if history:
            return ZenohPublisher(zenoh.ext.declare_advanced_publisher(
                self.session, key, congestion_control=congestion,
                priority=PRIORITIES[priority - 1],
                cache=zenoh.ext.CacheConfig(max_samples=history), publisher_detection=True))
        return ZenohPublisher(self.session.declare_publisher(
            key, congestion_control=congestion, priority=PRIORITIES[priority - 1]))

    def subscribe(self, key_expr: str, on_sample: Callable[[str, bytes], None],
                  history: int = 0) -> Declared:
        """``history``: also ask publishers that keep samples (now and as they come) for up to
        that many each (zenoh-ext's advanced subscriber, as zenoh-bridge-ros2dds receives
        transient_local topics)."""
        handler = direct(lambda sample: on_sample(str(sample.key_expr),
                                                   sample.payload.to_bytes()))
        if history:
            return Declared(zenoh.ext.declare_advanced_subscriber(
                self.session, key_expr, handler, history=zenoh.ext.HistoryConfig(
                    detect_late_publishers=True, max_samples=history)))
        return Declared(self.session.declare_subscriber(key_expr, handler))

    def serve(self, key: str, on_query: Callable[[str, bytes, Any], None]) -> Declared:
        def arrived(query: zenoh.Query) -> None:
            payload = query.payload
            on_query(str(query.key_expr), payload.to_bytes() if payload is not None else b"",
                     ZenohQuery(query, key))

        return Declared(self.session.declare_queryable(key, direct(arrived)))

    def query(self, key: str, payload: bytes, timeout: float,
              on_reply: Callable[[bytes], None], on_done: Callable[[int], None],
              attachment: bytes | None = None) -> None:
        answers = [0]

        def reply(got: zenoh.Reply) -> None:
            if got.ok is not None:
                answers[0] += 1
                on_reply(got.ok.payload.to_bytes())
            else:  # zenoh's own "Timeout", or a server's reply_err: no answer
                log.debug("zenoh: query on %s: %s", key,
                          got.err.payload.to_bytes()[:200] if got.err is not None else "?")

        try:
            self.session.get(key, direct(reply, lambda: on_done(answers[0])), payload=payload,
                             timeout=timeout, consolidation=NO_CONSOLIDATION,
                             attachment=attachment)
        except zenoh.ZError as exc:
            raise OSError(zenoh_message(exc)) from None

    def token(self, key: str) -> Declared:
        token = Declared(self.session.liveliness().declare_token(key),
                          lambda: self._tokens.discard(token))
        self._tokens.add(token)
        return token

    def watch(self, key_expr: str, on_change: Callable[[str, bool], None]) -> Declared:
        put = zenoh.SampleKind.PUT
        return Declared(self.session.liveliness().declare_subscriber(
            key_expr, direct(lambda sample: on_change(str(sample.key_expr), sample.kind == put)),
            history=True))

    def close(self) -> None:
        self.session.close()
        self._tokens.clear()
