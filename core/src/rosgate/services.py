"""Services across the link (docs/services.md): ``transmit`` is a :class:`CallerRoute`, a proxy
ROS server here whose calls cross the link; ``receive`` a :class:`ServerRoute`, which serves
calls from the link through a ROS client.

Wire (``framing: rosgate``): a request has ``FLAG_REQUEST``, the service's id and the call's id
in (epoch, seq); its answer echoes them with ``FLAG_REPLY`` (and ``FLAG_FAILED``, the body then
the reason in UTF-8). A call the bridge cannot complete is answered with :func:`failure` within
``timeout``, counted by reason and warned about.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable
from typing import Any

from .actions import Answer, Split
from .config import ServiceConfig
from .drops import Drop, Reason
from .errors import CodecError
from .keyring import NoKey
from .links.base import Link
from .routes import Route, SideSender
from .transport import Address
from .warn import BUGS
from .wire import envelope

# A proxy needs deep queues: with the default service QoS (depth 10) a server answered 11 of 50
# concurrent calls; with depth 1000 on both ends, 50 of 50 (DESIGN.md, measured).
QUEUE_DEPTH = 1000
# action_msgs: GoalStatus.STATUS_ABORTED, CancelGoal.Response.ERROR_REJECTED
GOAL_ABORTED = 6
CANCEL_REJECTED = 1
# a call waits this share of its timeout for its ROS server's discovery, polling (seconds)
DISCOVERY_SHARE = 0.8
DISCOVERY_POLL = 0.05


def failure(response_type: Any, reason: str) -> Any:
    """The answer a ROS caller gets when the bridge has none (ROS 2 services have no error
    channel): the default Response, with ``success = False`` and ``message = "rosgate: <reason>"``
    where the type has those fields."""
    response = response_type()
    fields = response_type.get_fields_and_field_types()
    if fields.get("success") == "boolean":
        response.success = False
    if fields.get("message") == "string":
        response.message = f"rosgate: {reason}"
    # an action's parts (rosgate.actions): a result that cannot come ends the goal aborted, a
    # cancel that cannot be delivered is rejected (a goal not accepted is send_goal's default)
    if fields.get("status") == "int8" and "result" in fields:
        response.status = GOAL_ABORTED
    if fields.get("return_code") == "int8" and "goals_canceling" in fields:
        response.return_code = CANCEL_REJECTED
    return response


class Call:
    """One call waiting for its outcome: answered exactly once, by an answer or a failure,
    whichever comes first (the answer, the deadline and a link failure race)."""

    __slots__ = ("_on_answer", "_on_failure", "_lock", "done")

    def __init__(self, on_answer: Callable[[Any], None], on_failure: Callable[[str], None]):
        self._on_answer = on_answer
        self._on_failure = on_failure
        self._lock = threading.Lock()
        self.done = False

    def answer(self, response: Any) -> bool:
        return self._settle(self._on_answer, response)

    def fail(self, reason: str, count: Callable[[], None] | None = None) -> bool:
        """``count`` runs before the failure is answered, so whoever sees it sees it counted."""
        return self._settle(self._on_failure, reason, count)

    def _settle(self, outcome: Callable[[Any], None], value: Any,
                count: Callable[[], None] | None = None) -> bool:
        with self._lock:
            first, self.done = not self.done, True
        if first:
            if count is not None:
                count()
            outcome(value)
        return first


class Deadlines:
    """One thread runs every call's deadline, in time order. Entries are not cancelled: a call
    answered in time makes its deadline a no-op (:class:`Call` settles once)."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._order = itertools.count()
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name="service-deadlines", daemon=True)
        self._thread.start()

    def after(self, seconds: float, action: Callable[[], None]) -> None:
        with self._cond:
            heapq.heappush(self._heap, (time.monotonic() + seconds, next(self._order), action))
            self._cond.notify()

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._closed and (
                        not self._heap or self._heap[0][0] > time.monotonic()):
                    self._cond.wait(self._heap[0][0] - time.monotonic() if self._heap else None)
                if self._closed:
                    return
                _, _, action = heapq.heappop(self._heap)
            try:
                action()
            except Exception:  # one bad deadline must not stop the others
                BUGS.bug("deadline_error", "a service call's deadline failed (a bug: please "
                                           "report it)")

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=2)


class ServiceCodec:
    """The entry's codec for the Request and for the Response."""

    def __init__(self, codec_cls: type, srv_type: Any, options: Any):
        self.request = codec_cls(srv_type.Request, options)
        self.response = codec_cls(srv_type.Response, options)

    @staticmethod
    def encode(codec: Any, message: Any) -> bytes:
        if codec.raw:
            from rclpy.serialization import serialize_message

            message = serialize_message(message)
        return codec.encode(message)

    @staticmethod
    def decode(codec: Any, data: bytes) -> Any:
        value = codec.decode(data)
        if not codec.raw:
            return value
        from rclpy.serialization import deserialize_message

        try:
            return deserialize_message(value, codec.msg_type)
        except Exception as exc:  # rclpy raises RMWError and others: any failure is unreadable
            raise CodecError(f"not a valid {codec.msg_type.__name__}: {exc}") from None


class ServiceRoute(Route):
    """What both sides of a service share: the entry, its codecs, counters and warnings."""

    def __init__(self, service: ServiceConfig, service_id: int, codec: ServiceCodec, keys: Any,
                 warner: Any, label: str, srv_type: Any, deadlines: Deadlines):
        # calls are not held while a link is down: the caller's timeout answers them instead
        super().__init__(service, service_id, codec, keys, warner, label)
        self.service = service
        self.srv_type = srv_type
        self.deadlines = deadlines

    def fail(self, call: Call, reason: Reason, detail: str) -> None:
        """Settle ``call`` with a failure, counted by ``reason`` (unless it is settled already)."""
        call.fail(detail, lambda: self.drop(reason, detail))

    def answering(self, respond: Callable[[Any], None]) -> Call:
        """A call whose outcome goes to ``respond`` as a Response: a failure as :func:`failure`."""
        response_type = self.srv_type.Response
        return Call(respond, lambda reason: respond(failure(response_type, reason)))


class CallerRoute(ServiceRoute):
    """``transmit``: a proxy ROS server here; each call crosses ``link`` (framing rosgate).
    ``mirrored``: the proxy exists only while the far side says a real server runs there
    (client/server; :class:`rosgate.proxies.Proxies`)."""

    def __init__(self, *args: Any, link: Link, destination: Callable[[], Address | None],
                 mirrored: bool = False):
        super().__init__(*args)
        self.link = link
        self.destination = destination
        self.mirrored = mirrored
        self.calls: dict[int, tuple[int, Call]] = {}  # seq -> (epoch, call)
        self._ids = itertools.count(1)

    def on_request(self, request: Any, respond: Callable[[Any], None]) -> None:
        """The ROS executor's thread: send the call and return; the answer comes later."""
        call = self.answering(respond)
        if self._refused(call):
            return
        to = self.destination()
        if to is None and self.link.datagram:
            self.fail(call, Drop.NO_PEER_YET, "the far side's address is not known yet")
            return
        # a call's id is (epoch, seq): the epoch of the key sealing it (a random one per start
        # with a static key), seq counting on across epochs, so no id repeats under one key
        seq = next(self._ids)
        try:
            epoch = self.keys.epoch()
            frame = self.seal(envelope.FLAG_REQUEST, epoch, seq,
                              self.codec.encode(self.codec.request, request))
        except NoKey:
            self.fail(call, Drop.NO_SESSION_KEY, "the session's handshake has not happened yet")
            return
        except Exception as exc:  # a codec or cipher bug must not leave the ROS caller waiting
            self.fail(call, Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
            return
        with self._lock:
            self.calls[seq] = (epoch, call)
        self.deadlines.after(self.service.timeout, lambda: self._expire(seq))
        # a drop on the way out fails the call at once
        sender = SideSender(self, self.delivery, lambda reason, detail="": self.fail(
            call, reason, detail or f"{self.link.name}: {reason}"))
        if not self.link.send(frame, sender, to):
            self._pop(seq)  # the link counted the drop, and answered the caller with it
            return
        self.counters.sent += 1
        self.counters.bytes_sent += len(frame)

    def on_reply(self, header: envelope.Header, frame: bytes) -> None:
        """A link's thread: match the answer to its call (after checking it is authentic)."""
        body = self.open(frame, header.epoch)
        if body is None:
            return
        call = self._pop(header.seq, header.epoch)
        if call is None:
            self.drop(Drop.LATE_ANSWER, f"answer to call {header.seq}, which was answered already "
                                        "or timed out")
            return
        self.counters.received += 1
        self.counters.bytes_received += len(frame)
        if self._refused(call):
            return
        if header.flags & envelope.FLAG_FAILED:
            self.fail(call, Drop.REMOTE_FAILURE, body.decode("utf-8", "replace")[:500])
            return
        try:
            response = self.codec.decode(self.codec.response, body)
        except CodecError as exc:
            self.fail(call, Drop.DECODE_ERROR, str(exc))
            return
        call.answer(response)

    def _refused(self, call: Call) -> bool:
        """Whether the far side's type differs: then the call fails, saying so."""
        if self.check.mismatch is None:
            return False
        self.fail(call, self.check.reason, self.check.mismatch)
        self.check.say()
        return True

    def fail_all(self, reason: Reason, detail: str) -> None:
        """Every waiting call fails (the session's line was lost): an action's goal ends
        aborted rather than waiting out its result's timeout."""
        with self._lock:
            waiting = [call for _, call in self.calls.values()]
            self.calls.clear()
        for call in waiting:
            self.fail(call, reason, detail)

    def _pop(self, seq: int, epoch: int | None = None) -> Call | None:
        """The call waiting under ``seq`` (and ``epoch``, when given), taken out."""
        with self._lock:
            waiting = self.calls.get(seq)
            if waiting is None or epoch is not None and waiting[0] != epoch:
                return None
            del self.calls[seq]
            return waiting[1]

    def _expire(self, seq: int) -> None:
        call = self._pop(seq)
        if call is not None:
            self.fail(call, Drop.TIMEOUT, f"no answer within {self.service.timeout:g} s")


class ServerRoute(ServiceRoute):
    """``receive``: calls from the far side, served by the ROS server here. A call beyond
    :data:`QUEUE_DEPTH` in progress fails at once (``too_many_calls``): a flood cannot pile up.
    ``goals``: an action's part as one client may use it (:class:`rosgate.actions.ClientGoals`):
    a call about other clients' goals is answered here, a cancel of many goals split.
    ``link`` and ``destination`` given: it says on ``link`` whether a real ROS server runs here
    (``served``), so the far side's proxy exists only while one does."""

    def __init__(self, *args: Any, goals: Any = None, link: Link | None = None,
                 destination: Callable[[], Address | None] | None = None,
                 served: bool = False) -> None:
        super().__init__(*args)
        self.in_flight = 0
        self.goals = goals
        self.mirror = link is not None
        if link is not None and destination is not None:
            self.link, self.destination = link, destination
        self.served = served

    def said(self) -> dict[str, Any]:
        said = super().said()
        if self.mirror:
            said["served"] = self.served
        return said

    def serve(self, request: Any, call: Call) -> None:
        """Call the ROS server here; ``call`` gets its answer or a failure within ``timeout``.
        An undiscovered server is polled for up to :data:`DISCOVERY_SHARE` of the timeout, so
        that the failure still reaches the caller, whose bridge waits ``timeout`` in all."""
        start = time.monotonic()
        wait_until = start + self.service.timeout * DISCOVERY_SHARE
        client = self.entity

        def when_ready() -> None:
            if client.service_is_ready():
                self._call(request, call, start)
            elif call.done:
                return
            elif time.monotonic() >= wait_until:
                self.fail(call, Drop.NO_SERVER, f"no ROS server {self.service.service} is running "
                                                "on the serving side")
            else:
                self.deadlines.after(DISCOVERY_POLL, when_ready)

        when_ready()

    def _call(self, request: Any, call: Call, start: float) -> None:
        client = self.entity
        future = client.call_async(request)
        future.add_done_callback(lambda f: self._answered(f, call))

        def expire() -> None:
            if not future.done():
                client.remove_pending_request(future)
                self.fail(call, Drop.TIMEOUT, f"the ROS server {self.service.service} did not "
                                          f"answer within {self.service.timeout:g} s")
        self.deadlines.after(max(0.0, start + self.service.timeout - time.monotonic()), expire)

    def _answered(self, future: Any, call: Call) -> None:
        if future.cancelled() or future.exception() is not None:
            self.fail(call, Drop.SERVER_ERROR, f"the ROS call failed: {future.exception()}")
        elif not call.answer(future.result()):
            self.drop(Drop.LATE_ANSWER, f"{self.service.service} answered after the timeout")

    def on_request(self, header: envelope.Header, frame: bytes, link: Link,
                   source: Address) -> None:
        """A link's thread: a call from the far side (framing rosgate), answered on ``link`` to
        where it came from."""
        size = len(frame)
        if size > envelope.SIZE + self.service.max_request:
            self.drop(Drop.TOO_LARGE, f"request of {size - envelope.SIZE} bytes, "
                                      f"max_request is {self.service.max_request}")
            return
        payload = self.admit(header, frame)
        if payload is None:
            return
        if self.check.mismatch is not None:
            self.refuse(header, link, source)
            return
        if self.check.awaiting and self.check.hold(size, lambda agreed: self.accept(
                header, payload, size, link, source) if agreed else self.refuse(
                header, link, source)):
            return  # until the far side says its type (rosgate.announce)
        self.accept(header, payload, size, link, source)

    def refuse(self, header: envelope.Header, link: Link, source: Address) -> None:
        """A call of another type than this side's: answered as a failure, never served."""
        self.refuse_type()
        reason = self.check.mismatch or f"{self.label}: refused, the far side's type differs"
        self.reply(header, link, source, envelope.FLAG_FAILED, reason.encode())

    def reply(self, header: envelope.Header, link: Link, source: Address, flags: int,
              body: bytes) -> None:
        """The answer to the call of ``header``, back on ``link`` to where it came from."""
        try:
            frame = self.seal(envelope.FLAG_REPLY | flags, header.epoch, header.seq, body)
        except NoKey:  # the request's key expired while the ROS server took its time
            self.drop(Drop.NO_SESSION_KEY, "the request's session key is gone")
            return
        if link.send(frame, self, source):
            self.counters.sent += 1
            self.counters.bytes_sent += len(frame)

    def accept(self, header: envelope.Header, payload: bytes, size: int, link: Link,
               source: Address) -> None:
        """A call past its checks: served by the ROS server here, answered on ``link``."""
        try:
            request = self.codec.decode(self.codec.request, payload)
        except CodecError as exc:
            self.drop(Drop.DECODE_ERROR, str(exc))
            return
        self.counters.received += 1
        self.counters.bytes_received += size
        goals = self.goals
        screened = goals.screen(request) if goals is not None else None
        if isinstance(screened, Answer):
            if screened.reason is not None:
                self.drop(screened.reason, screened.detail)
            self.reply(header, link, source, 0,
                       self.codec.encode(self.codec.response, screened.response))
            return
        with self._lock:
            busy = self.in_flight >= QUEUE_DEPTH
            if not busy:
                self.in_flight += 1
        if busy:
            self.drop(Drop.TOO_MANY_CALLS, f"{QUEUE_DEPTH} calls in progress")
            self.reply(header, link, source, envelope.FLAG_FAILED, f"the serving bridge has "
                       f"{QUEUE_DEPTH} calls of {self.service.service} in progress".encode())
            return

        def reply(flags: int, body: bytes) -> None:
            with self._lock:
                self.in_flight -= 1
            self.reply(header, link, source, flags, body)

        def answered(response: Any) -> None:
            if goals is not None:
                goals.answered(request, response)
            try:
                body = self.codec.encode(self.codec.response, response)
            except Exception as exc:
                self.drop(Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
                reply(envelope.FLAG_FAILED, b"the serving bridge could not encode the answer")
                return
            reply(0, body)

        def failed(reason: str) -> None:
            if goals is not None:
                goals.answered(request, None)
            reply(envelope.FLAG_FAILED, reason.encode())

        call = Call(answered, failed)
        if isinstance(screened, Split):
            self.serve_split(screened.requests, screened.merge, call)
        else:
            self.serve(request, call)

    def serve_split(self, requests: list[Any], merge: Callable[[list[Any]], Any],
                    call: Call) -> None:
        """Serve ``requests`` (one call split in several), then answer ``call`` with
        ``merge`` of their answers, each ``None`` that failed."""
        answers: list[Any] = [None] * len(requests)
        left = [len(requests)]

        def one(index: int) -> Call:
            def done(response: Any) -> None:
                answers[index] = response
                settled()

            return Call(done, lambda reason: settled())

        def settled() -> None:
            with self._lock:
                left[0] -= 1
                last = left[0] == 0
            if last:
                call.answer(merge(answers))

        for index, request in enumerate(requests):
            self.serve(request, one(index))


def deep_qos() -> Any:
    from rclpy.qos import QoSProfile

    return QoSProfile(depth=QUEUE_DEPTH)
