"""Services with microcontrollers: the CVRA call pattern (``framing: serial_datagram``).

One stream connection (TCP) per call. The caller writes one serial datagram (serial_datagram.py)
whose payload is the service's ``remote`` name and the request, laid out as ``[name, args]`` or
as ``name`` then ``args`` (:mod:`rosgate.wire.names`; the entry's ``layout`` picks what this side
writes, and either is read); the server writes its answer as one plain MessagePack value (any
value: the codec maps it onto the response) and closes the connection.

* ``direction: receive`` -> :class:`CallServer`: the bridge listens on ``listen:port`` and a
  microcontroller calls ROS services here. Several services may share the port: the name tells
  them apart. A connection must deliver its request within the longest ``timeout`` of the port's
  services (else it is closed: ``request_timeout``), and may not fall silent for
  ``bridge.limits.idle_timeout`` meanwhile (``idle_timeout``); with the bridge's limits on
  connections per source, idle sockets cannot hold the port's places against a
  microcontroller. The answer, or a failure answer (see rosgate.services), is written within the
  service's ``timeout``, then the bridge closes.
* ``direction: transmit`` -> :class:`CvraCallerRoute`: a proxy ROS server here; each call
  connects to ``peer:port``, writes the request and reads until the answer decodes (or the peer
  closes). A microcontroller that keeps the connection open after answering is closed by the
  bridge; one that never answers fails the call at ``timeout``. One that closes without a byte
fails the call (``no_answer``), unless the entry says ``no_answer: nil``: then the call is
answered as if it had answered nil (CVRA's Python server sends nothing when its handler returns
None).

Every bad request (bad CRC or escape, too short, over ``max_request``, an unknown name, a map
that does not decode) is dropped, counted and warned about; the connection is closed without an
answer, as a microcontroller's own server would.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from rosgate import (
    BUGS,
    Address,
    Call,
    CodecError,
    Drop,
    Layout,
    NameMissing,
    Reason,
    ServerRoute,
    ServiceRoute,
    StreamConnection,
    StreamTransport,
    Transport,
    declare,
    pack_name,
    split_name,
)

from . import serial_datagram

log = logging.getLogger("rosgate")

IDLE_TIMEOUT = declare("idle_timeout", "a caller silent for `bridge.limits.idle_timeout` before "
                                       "its request was whole")
CLOSED_EARLY = declare("closed_early", "a caller that closed before its request was whole")
REQUEST_TIMEOUT = declare("request_timeout", "a caller whose request was not whole within the "
                                             "longest `timeout` of the port's services")
UNNAMED_REQUEST = declare("unnamed_request", "a request that does not start with a service's name")
CONNECT_FAILED = declare("connect_failed", "the microcontroller could not be connected to")
NO_ANSWER = declare("no_answer", "the microcontroller closed without a byte of answer")

MAX_CONNECTIONS = 64   # calls served at once on one port; more are closed at once and counted
CALLER_THREADS = 16    # connections a calling route has open at once; more calls wait their turn
CHUNK = 4096
POLL = 0.2  # seconds a receive waits before looking whether the bridge is stopping
NIL = b"\xc0"  # MessagePack's nil


class CallServer:
    """Serves microcontrollers' calls on one port (direction receive), for every service there.
    The services' names are read with the codec of the first (only msgpack names requests)."""

    def __init__(self, name: str, link_drop: Callable[[Any, Reason, str], None],
                 idle_timeout: float = 2.0):
        self.name = name
        self.link_drop = link_drop  # counts what belongs to no service (by port)
        self.idle_timeout = idle_timeout
        self.routes: dict[str, ServerRoute] = {}
        self._slots = threading.BoundedSemaphore(MAX_CONNECTIONS)

    def add(self, route: ServerRoute) -> None:
        self.routes[route.service.remote] = route

    @property
    def wait(self) -> float:
        return max(r.service.timeout for r in self.routes.values())

    @property
    def max_request(self) -> int:
        return max(r.service.max_request for r in self.routes.values())

    def accepted(self, connection: StreamConnection, peer: Address) -> None:
        if not self._slots.acquire(blocking=False):
            self.drop(Drop.TOO_MANY_CONNECTIONS, f"{MAX_CONNECTIONS} calls in progress; "
                                                 f"closed a connection from {peer[0]}")
            connection.close()
            return
        threading.Thread(target=self._serve, args=(connection, peer), daemon=True,
                         name=f"call-{self.name}").start()

    def drop(self, reason: Reason, detail: str) -> None:
        self.link_drop(self, reason, detail)

    def _serve(self, connection: StreamConnection, peer: Address) -> None:
        try:
            payload = self._read_request(connection, peer)
            if payload is not None:
                answer = self._answer(payload, peer)
                if answer is not None:
                    connection.send(answer)
        except OSError as exc:
            log.debug("%s: connection from %s: %s", self.name, peer[0], exc)
        except Exception:  # a bug, not the peer's bytes: keep serving the others
            BUGS.bug("call_error", f"{self.name}: error while serving a call from {peer[0]} "
                                   "(a bug: please report it)")
            self.drop(Drop.HANDLER_ERROR, f"from {peer[0]}")
        finally:
            connection.close()
            self._slots.release()

    def _read_request(self, connection: StreamConnection, peer: Address) -> bytes | None:
        errors: list[tuple[Reason, str]] = []
        decoder = serial_datagram.Decoder(lambda *error: errors.append(error), self.max_request)
        deadline = time.monotonic() + self.wait
        heard = time.monotonic()
        received = 0
        while (left := deadline - time.monotonic()) > 0:
            data = connection.receive(CHUNK, min(left, POLL))
            if data is None:
                if time.monotonic() - heard > self.idle_timeout:
                    self.drop(IDLE_TIMEOUT, f"{peer[0]} silent for {self.idle_timeout:g} s "
                                          f"after {received} bytes")
                    return None
                continue
            heard = time.monotonic()
            if not data:
                self.drop(CLOSED_EARLY, f"{peer[0]} closed after {received} bytes, "
                                      "before a whole request")
                return None
            received += len(data)
            for payload in decoder.feed(data):
                return payload  # one call per connection: anything after it is ignored
            if errors:
                reason, detail = errors[0]
                self.drop(reason, f"request from {peer[0]}: {detail}")
                return None
        said = "said nothing" if not received else f"sent {received} bytes, no whole request"
        self.drop(REQUEST_TIMEOUT, f"{peer[0]} {said} within {self.wait:g} s")
        return None

    def _answer(self, payload: bytes, peer: Address) -> bytes | None:
        """Serve one request; the plain MessagePack answer, or None to close without one."""
        try:
            name, rest = split_name(payload)
        except NameMissing as exc:
            self.drop(UNNAMED_REQUEST, f"from {peer[0]}: {exc}")
            return None
        route = self.routes.get(name)
        if route is None:
            self.drop(Drop.UNKNOWN_SERVICE, f"{name!r} from {peer[0]} (served here: "
                                            f"{', '.join(self.routes)})")
            return None
        if len(payload) > route.service.max_request:
            route.drop(Drop.TOO_LARGE, f"request of {len(payload)} bytes, max_request is "
                                       f"{route.service.max_request}")
            return None
        codec = route.codec
        try:
            request = codec.decode(codec.request, rest)
        except CodecError as exc:
            route.drop(Drop.DECODE_ERROR, str(exc))
            return None
        route.counters.received += 1
        route.counters.bytes_received += len(payload)
        done = threading.Event()
        answer: list[Any] = []

        def settle(response: Any) -> None:
            answer.append(response)
            done.set()

        route.serve(request, route.answering(settle))
        if not done.wait(route.service.timeout + 5):  # serve() settles within the timeout
            return None
        try:
            data = codec.encode(codec.response, answer[0])
        except Exception as exc:
            route.drop(Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
            return None
        route.counters.sent += 1
        route.counters.bytes_sent += len(data)
        return data


class CvraCallerRoute(ServiceRoute):
    """``transmit``: a proxy ROS server here; each call is one connection to the microcontroller."""

    def __init__(self, *args: Any, transport: Transport, address: Address):
        super().__init__(*args)
        assert isinstance(transport, StreamTransport)
        self.transport = transport
        self.address = address
        self._pool = ThreadPoolExecutor(CALLER_THREADS, thread_name_prefix=f"call-{self.label}")

    def on_request(self, request: Any, respond: Any) -> None:
        """The ROS executor's thread: hand the call to a connection thread and return."""
        call = self.answering(respond)
        self.deadlines.after(self.service.timeout, lambda: self.fail(
            call, Drop.TIMEOUT, f"no answer from {self.address[0]}:{self.address[1]} within "
                             f"{self.service.timeout:g} s"))
        self._pool.submit(self._call, request, call, time.monotonic() + self.service.timeout)

    def _call(self, request: Any, call: Call, deadline: float) -> None:
        codec = self.codec
        try:
            # serial_datagram entries have a MessagePack codec: never a raw one
            frame = serial_datagram.encode(pack_name(self.service.remote,
                                                     Layout(self.service.layout))
                                           + codec.encode(codec.request, request))
        except Exception as exc:
            self.fail(call, Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
            return
        left = deadline - time.monotonic()
        if call.done or left <= 0:
            return  # timed out while waiting for a connection thread
        try:
            connection = self.transport.connect(self.address, left)
        except OSError as exc:
            self.fail(call, CONNECT_FAILED, f"{self.address[0]}:{self.address[1]}: {exc}")
            return
        try:
            connection.send(frame)
            self.counters.sent += 1
            self.counters.bytes_sent += len(frame)
            self._read_answer(connection, call, deadline)
        except OSError as exc:
            self.fail(call, Drop.LINK_DOWN, f"{self.address[0]}:{self.address[1]}: {exc}")
        finally:
            connection.close()

    def _read_answer(self, connection: StreamConnection, call: Call, deadline: float) -> None:
        """Read until the answer decodes; a peer may close right after it, or keep the
        connection open (then the bridge closes it)."""
        codec = self.codec
        data = b""
        while not call.done and (left := deadline - time.monotonic()) > 0:
            chunk = connection.receive(CHUNK, min(left, POLL))
            if chunk is None:
                continue
            if chunk and len(data) + len(chunk) > self.service.max_request:
                self.fail(call, Drop.TOO_LARGE, f"answer over {self.service.max_request} bytes")
                return
            data += chunk
            silent = not data and self.service.no_answer == "nil"
            try:
                response = codec.decode(codec.response, NIL if silent else data)
            except CodecError as exc:
                if chunk:
                    continue  # perhaps not all of it yet
                self.fail(call, Drop.DECODE_ERROR if data else NO_ANSWER,
                          str(exc) if data else "closed without an answer")
                return
            self.counters.received += 1
            self.counters.bytes_received += len(data)
            if silent:
                log.debug("%s: %s closed without a byte: answered as nil (no_answer: nil)",
                          self.label, self.address[0])
            if not call.answer(response):
                self.drop(Drop.LATE_ANSWER, f"answer from {self.address[0]} after the timeout")
            return

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
