"""The client role: connects its main line to the server, sends its topics, builds routes from
the answer, and starts over when the main line is lost.

Stream topics without a port ride the main line; datagram topics without a port use the
server's main port number on that transport. The client starts every connection, so it can sit
behind NAT.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Any

from . import envelope
from .config import service_to_mapping, topic_to_mapping
from .errors import LinkError
from .links import DatagramLink, Link, StreamLink
from .mainline import HANDSHAKE_TIMEOUT, PROTOCOL, control, hello_datagram, parse_control
from .roles import Connector, LinkSlot, Role
from .transport import Address

if TYPE_CHECKING:
    from .engine import Engine, Prepared

log = logging.getLogger("rosgate")


class ClientRole(Role):
    def __init__(self, engine: Engine):
        super().__init__(engine)
        self.main = LinkSlot(f"main->{self.cfg.server}")
        self.session: int | None = None
        self.token = b""
        self.server_name: str | None = None
        self.connected = threading.Event()
        self.hello_to: set[tuple[DatagramLink, Address]] = set()  # every server port we use
        self._welcome: dict[str, Any] | None = None
        self._answer = threading.Event()
        main = engine.transports[self.cfg.main_line]
        self.connector = Connector(engine, main, engine.main_address, self.main, self._on_main_frame,
                                   self._handshake)

    def start(self) -> None:
        self.connector.start()
        self._pinger = threading.Thread(target=self._ping_loop, name="client-ping", daemon=True)
        self._pinger.start()

    def stop(self) -> None:
        self.connector.close()
        super().stop()

    def _on_main_frame(self, frame: bytes, link: Link, source: Address) -> None:
        if frame[3:4] and frame[3] & envelope.FLAG_CONTROL and frame[:2] == envelope.MAGIC:
            message = parse_control(frame)
            if message is None:
                self.engine.link_drop(link, "bad_control", "unreadable control message")
            elif message["type"] in ("welcome", "refused"):
                self._welcome = message
                self._answer.set()
            return
        self.engine.on_frame(frame, link, source)

    def _handshake(self, link: StreamLink) -> bool:
        """Send our topics; build the routes from the server's answer."""
        self._teardown()
        self._answer.clear()
        self._welcome = None
        self.main.current = link
        link.send(control({"type": "hello", "protocol": PROTOCOL, "name": self.cfg.name,
                           "topics": [topic_to_mapping(p.config) for p in self.engine.topics],
                           "services": [service_to_mapping(p.config)
                                        for p in self.engine.services]}), 0)
        if not self._answer.wait(HANDSHAKE_TIMEOUT) or self._welcome is None:
            log.warning("%s: no answer to the handshake from %s", self.cfg.name, self.cfg.server)
            return False
        answer = self._welcome
        if answer["type"] == "refused":
            log.error("%s: the server refused our topics: %s", self.cfg.name, answer.get("error"))
            return False
        try:
            self._build(answer)
        except (KeyError, TypeError, ValueError, LinkError) as exc:
            log.error("%s: cannot use the server's answer: %s", self.cfg.name, exc)
            self._teardown()
            return False
        log.info("%s: connected to server %r at %s", self.cfg.name, self.server_name, self.cfg.server)
        self.connected.set()
        threading.Thread(target=self._watch, args=(link,), daemon=True).start()
        return True

    def _build(self, answer: dict[str, Any]) -> None:
        engine = self.engine
        ids = [int(i) for i in answer["topic_ids"] + answer.get("service_ids", [])]
        if len(ids) != len(engine.topics) + len(engine.services):
            raise ValueError("topic id count does not match")
        self.session = int(answer["session"])
        self.token = bytes.fromhex(answer["token"])
        self.server_name = str(answer["name"])
        host, main_port = engine.main_address
        for p, topic_id in zip([*engine.topics, *engine.services], ids):
            t = p.config
            label = f"{p.name} ({'to' if t.direction == 'transmit' else 'from'} {self.server_name})"
            if p.transport.stream:
                if t.port is None:
                    link: Link = self.main
                else:
                    link = self._dedicated_stream(p, (host, t.port))
                self.add(engine.make_route(p, topic_id, label, link))
            else:
                to = (host, t.port or main_port)
                link = self.datagram_link(p.transport, ("::" if ":" in host else "0.0.0.0", 0))
                self.add(engine.make_route(p, topic_id, label, link, lambda to=to: to))
                self.hello_to.add((link, to))
        self._say_hello()

    def _dedicated_stream(self, p: Prepared, address: Address) -> LinkSlot:
        slot = LinkSlot(f"{p.config.transport}->{address[0]}:{address[1]}")

        def introduce(link: StreamLink) -> bool:
            assert self.session is not None
            return link.send(hello_datagram(self.session, self.token), 0)

        connector = Connector(self.engine, p.transport, address, slot, self.engine.on_frame,
                              introduce)
        connector.start()
        self._extra.append(connector)
        return slot

    def _say_hello(self) -> None:
        if self.session is None:
            return
        hello = hello_datagram(self.session, self.token)
        for link, to in list(self.hello_to):
            link.send(hello, 0, to)

    def _watch(self, link: StreamLink) -> None:
        link.closed.wait()
        if not self.engine.stopping.is_set():
            log.warning("%s: main line to %s lost; reconnecting", self.cfg.name, self.cfg.server)
        self.connected.clear()
        self._teardown()

    def _ping_loop(self) -> None:
        while not self.engine.stopping.wait(self.cfg.heartbeat):
            if self.connected.is_set():
                self.main.send(control({"type": "ping"}), 0)
                self._say_hello()

    def _teardown(self) -> None:
        for connector in getattr(self, "_extra", []):
            connector.close()
        self._extra: list[Connector] = []
        super().stop()
        with self._lock:
            links = list(self.datagram_links.values())
            self.datagram_links.clear()
            self.hello_to.clear()
        for link in links:
            link.close()
