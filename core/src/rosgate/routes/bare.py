"""``framing: none``: a topic's messages as bare datagrams, the codec's bytes alone, told apart
on a shared port by the name in front of each (:mod:`rosgate.wire.names`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..drops import Drop, Reason
from ..links.base import Link
from ..transport import Address
from ..wire.names import LAYOUT_DEFAULT, Layout, NameMissing, call_shaped, pack_name, split_name


class BareFraming:
    """``framing: none``: one datagram per message, the codec's bytes alone (no flags) — after
    the topic's ``remote`` name (:mod:`rosgate.wire.names`) when the codec writes MessagePack
    (the microcontroller format), so several topics can share a port (:class:`BarePort`)."""

    def __init__(self, name: str | None, layout: Layout = LAYOUT_DEFAULT):
        self.prefix = pack_name(name, layout) if name is not None else b""

    def frame(self, route: Any, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        return self.prefix + payload

class BarePort:
    """The receiving topics of one port with ``framing: none``: told apart by the name in front
    of each datagram when their codec writes MessagePack, else the port's only topic.
    ``link_drop(link, reason, detail)`` counts a datagram that belongs to none of them."""

    def __init__(self, named: bool, link_drop: Callable[[Link, Reason, str], None]):
        self.named = named
        self.link_drop = link_drop
        self.routes: dict[str, Any] = {}
        self.only: Any = None
        self.calls_elsewhere = False

    def leave_calls(self) -> None:
        """Calls and answers on this line are served by entries of their own (a serial line
        with calls): pass them over here, uncounted."""
        self.calls_elsewhere = True

    def add(self, route: Any, names: set[str]) -> None:
        if self.named:
            self.routes.update(dict.fromkeys(names, route))
        else:
            self.only = route

    def on_frame(self, datagram: bytes, link: Link, source: Address) -> None:
        if not self.named:
            if self.only is not None:
                self.only.deliver(datagram, len(datagram))
            return
        if self.calls_elsewhere and call_shaped(datagram):
            return
        try:
            name, rest = split_name(datagram)
        except NameMissing as exc:
            self.link_drop(link, Drop.UNNAMED_FRAME, f"{len(datagram)} bytes from {source}: {exc}")
            return
        route = self.routes.get(name)
        if route is None:
            self.link_drop(link, Drop.UNKNOWN_TOPIC, f"name {name!r} from {source}")
            return
        route.deliver(rest, len(datagram))
