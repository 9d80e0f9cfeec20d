"""Calls with a microcontroller on a serial line (``framing: serial_datagram`` on a datagram
transport that is one line, ``transport: serial`` with ``multiplex: false``).

A line has no connection per call to pair an answer with its request, so the call carries an id
and its answer names it; both are one serial datagram, as messages are:

* a call: ``[name, args, id]``, a MessagePack array of three, ``id`` an unsigned integer the
  caller picks (the bridge: one count for all its calling entries);
* its answer: ``[id, value]``, an array of two whose first item is that integer (a message's is
  a name: a string), ``value`` any MessagePack value the codec maps onto the response.

Either side calls. The bridge's calls wait for their answer until the service's ``timeout``
(``timeout``, counted); an answer that names no call waiting (late, or another caller's: every
calling entry on the line sees every answer) is left alone. A call for a service not served on
the line is counted ``unknown_service`` and not answered. Messages (``[name, args]``) on the
same line are the topics' entries' business.
"""

from __future__ import annotations

import itertools
import logging
import threading
from typing import Any

import msgpack

from rosgate import (
    BUGS,
    Address,
    Call,
    CodecError,
    DatagramEndpoint,
    DatagramTransport,
    Drop,
    Reason,
    ServerRoute,
    ServiceRoute,
)

log = logging.getLogger("rosgate")

CALL, ANSWER = 3, 2  # the items of a call's array and of an answer's
IDS = 1 << 32
POLL = 0.2  # seconds a receive waits before looking whether the line is closing
#: one count for every calling entry of the bridge: they share the line, and each sees every
#: answer, so no two calls waiting at once may have the same id
_next_id = itertools.count(1)


def read(datagram: bytes) -> tuple[int, Any, bytes] | None:
    """A call: ``(id, name, the bytes of its args)``; an answer: ``(id, None, the bytes of its
    value)``; None for anything else (a message: not the calls' business)."""
    if not datagram or datagram[0] not in (0x90 | CALL, 0x90 | ANSWER):
        return None
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=len(datagram) + 1)
    unpacker.feed(datagram)
    try:
        items = unpacker.read_array_header()
        first = unpacker.unpack()
        if items == ANSWER and isinstance(first, int) and not isinstance(first, bool):
            return first, None, datagram[unpacker.tell():]
        if items == CALL and isinstance(first, str):
            start = unpacker.tell()
            unpacker.skip()
            end = unpacker.tell()
            ident = unpacker.unpack()
            if isinstance(ident, int) and not isinstance(ident, bool) \
                    and unpacker.tell() == len(datagram):
                return ident, first, datagram[start:end]
    except (ValueError, msgpack.ExtraData, msgpack.OutOfData, msgpack.FormatError,
            msgpack.StackError):
        pass
    return None


def is_call(datagram: bytes) -> bool:
    """Whether a datagram is a call or an answer (a topic port leaves those to the calls)."""
    return read(datagram) is not None


class LineEnd:
    """One endpoint on the line and the thread that reads it: ``on_datagram(datagram, source)``
    for every call and answer."""

    def __init__(self, transport: DatagramTransport, address: Address, name: str,
                 on_datagram: Any):
        self.endpoint: DatagramEndpoint = transport.bind(address)
        self.on_datagram = on_datagram
        self.closed = threading.Event()
        threading.Thread(target=self._read, name=name, daemon=True).start()

    def _read(self) -> None:
        while not self.closed.is_set():
            try:
                got = self.endpoint.receive(POLL)
            except OSError:
                self.closed.wait(POLL)
                continue
            if got is None:
                continue
            try:
                self.on_datagram(*got)
            except Exception:  # a bug, not the board's bytes: keep reading
                BUGS.bug("call_error", "error on a serial line's calls (a bug: please report it)")

    def send(self, datagram: bytes, to: Address) -> None:
        self.endpoint.send(datagram, to)

    def close(self) -> None:
        self.closed.set()
        self.endpoint.close()


class LineCallerRoute(ServiceRoute):
    """``transmit``: a proxy ROS server here; each call is ``[name, args, id]`` on the line."""

    def __init__(self, *args: Any, transport: DatagramTransport, address: Address):
        super().__init__(*args)
        self.address = address
        self._waiting: dict[int, Call] = {}
        self._lock = threading.Lock()
        self.line = LineEnd(transport, address, f"calls-{self.label}", self._on_datagram)

    def on_request(self, request: Any, respond: Any) -> None:
        call = self.answering(respond)
        ident = next(_next_id) % IDS
        codec = self.codec
        try:
            datagram = (bytes((0x90 | CALL,)) + msgpack.packb(self.service.remote)
                        + codec.encode(codec.request, request) + msgpack.packb(ident))
        except Exception as exc:
            self.fail(call, Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
            return
        with self._lock:
            self._waiting[ident] = call
        self.deadlines.after(self.service.timeout, lambda: self._expire(ident))
        try:
            self.line.send(datagram, self.address)
        except OSError as exc:
            self._forget(ident)
            self.fail(call, Drop.LINK_DOWN, f"{self.address[0]}: {exc}")
            return
        self.counters.sent += 1
        self.counters.bytes_sent += len(datagram)

    def _forget(self, ident: int) -> Call | None:
        with self._lock:
            return self._waiting.pop(ident, None)

    def _expire(self, ident: int) -> None:
        call = self._forget(ident)
        if call is not None:
            self.fail(call, Drop.TIMEOUT, f"no answer to call {ident} from {self.address[0]} "
                                          f"within {self.service.timeout:g} s")

    def _on_datagram(self, datagram: bytes, source: Address) -> None:
        found = read(datagram)
        if found is None or found[1] is not None:
            return  # a message, or a call: another entry's
        ident, _, value = found
        with self._lock:
            if ident not in self._waiting:
                return  # another caller's on this line (each counts its own ids) or late
            call = self._waiting.pop(ident)
        codec = self.codec
        try:
            response = codec.decode(codec.response, value)
        except CodecError as exc:
            self.fail(call, Drop.DECODE_ERROR, str(exc))
            return
        self.counters.received += 1
        self.counters.bytes_received += len(datagram)
        call.answer(response)

    def close(self) -> None:
        self.line.close()


class LineCallServer:
    """``receive``: the microcontroller's calls on the line, for every service of the entry's
    port; answered ``[id, value]`` to where they came from."""

    def __init__(self, name: str, link_drop: Any, transport: DatagramTransport,
                 address: Address):
        self.name = name
        self.link_drop = link_drop
        self.routes: dict[str, ServerRoute] = {}
        self.line = LineEnd(transport, address, f"calls-{name}", self._on_datagram)

    def add(self, route: ServerRoute) -> None:
        self.routes[route.service.remote] = route

    def drop(self, reason: Reason, detail: str) -> None:
        self.link_drop(self, reason, detail)

    def _on_datagram(self, datagram: bytes, source: Address) -> None:
        found = read(datagram)
        if found is None or found[1] is None:
            return  # a message, or an answer: another entry's
        ident, name, args = found
        route = self.routes.get(name)
        if route is None:
            self.drop(Drop.UNKNOWN_SERVICE, f"{name!r} (served here: {', '.join(self.routes)})")
            return
        if len(datagram) > route.service.max_request:
            route.drop(Drop.TOO_LARGE, f"request of {len(datagram)} bytes, max_request is "
                                       f"{route.service.max_request}")
            return
        codec = route.codec
        try:
            request = codec.decode(codec.request, args)
        except CodecError as exc:
            route.drop(Drop.DECODE_ERROR, str(exc))
            return
        route.counters.received += 1
        route.counters.bytes_received += len(datagram)

        def settle(response: Any) -> None:
            try:
                answer = (bytes((0x90 | ANSWER,)) + msgpack.packb(ident)
                          + codec.encode(codec.response, response))
            except Exception as exc:
                route.drop(Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
                return
            try:
                self.line.send(answer, source)
            except OSError as exc:
                route.drop(Drop.SEND_ERROR, str(exc))
                return
            route.counters.sent += 1
            route.counters.bytes_sent += len(answer)

        route.serve(request, route.answering(settle))

    def close(self) -> None:
        self.line.close()
