"""Where an entry's frames go: its key on a bus (as the bus role makes it), else its addresses —
the server's host or the peer's, the entry's port — as its transport accepts them; and what a
point-to-point entry needs and a bus entry must not have.
"""

from __future__ import annotations

from typing import Any

from ..bus import BusTransport
from ..config import BridgeConfig, Direction, Framing, Role, ServiceConfig, TopicConfig
from ..errors import ConfigError
from ..plugins import Plugins
from ..spec import TopicSpec
from ..transport import Address, DatagramTransport, StreamTransport, Transport
from ..wire.envelope import topic_id_for
from .made import ErrorMaker, PluginMaker

ANY_IP = "0.0.0.0"
NO_ADDRESS: Address = ("", 0)  # bus entries have a key instead


class Placer(PluginMaker):
    """Places entries: a bus key or addresses, checked."""

    def __init__(self, config: BridgeConfig, plugins: Plugins):
        super().__init__(config, plugins)
        self.main_address: Address | None = None  # client and server: the server's, once planned

    def _where(self, entry: TopicConfig | ServiceConfig, key: str, transport: Transport,
               error: ErrorMaker) -> dict[str, Any]:
        """Where an entry's frames go: its key on a bus, else its addresses."""
        if isinstance(transport, BusTransport):
            return {"address": NO_ADDRESS, "local": NO_ADDRESS,
                    "key": self._bus_key(transport, entry, key, error)}
        self._point_to_point(entry, key, transport, error)
        address, local = self._addresses(transport, entry, key, error)
        return {"address": address, "local": local}

    def _bus_key(self, transport: BusTransport, entry: TopicConfig | ServiceConfig, key: str,
                 error: ErrorMaker) -> str:
        """A bus entry's key, as its bus role makes it. Bus entries live in peer-role files (no
        main line: the bus finds the others) and have no port."""
        kind, cfg = _kind(entry), self.config
        if cfg.role is not Role.PEER:
            raise error(f"{key}.transport", f"{entry.transport} is a bus: its {kind}s belong in a "
                        f"file of role peer (no main line: {entry.transport} finds the others)",
                        f"use role: peer for this bridge, or another transport for this {kind}")
        if entry.port is not None:
            raise error(f"{key}.port", f"port: does not apply to a {entry.transport} {kind}: "
                        "it is published on a key (remote:)", "remove port: from this entry")
        role = self.bus_role(transport, f"{key}.transport", error)
        try:
            return role.key(transport, entry, cfg.name)
        except ConfigError as exc:
            raise error(f"{key}.{exc.key}", exc.message, exc.fix) from None

    def _point_to_point(self, entry: TopicConfig | ServiceConfig, key: str, transport: Transport,
                        error: ErrorMaker) -> None:
        """What only a bus takes: placeholders, a key for remote; and what point-to-point
        entries need: a port (a peer's; a client's off the main line), peer: for the far host."""
        cfg, kind = self.config, _kind(entry)
        name = entry.topic if isinstance(entry, TopicConfig) else entry.service
        if "{" in name or "}" in name:
            raise error(f"{key}.{kind}", f"placeholders such as {{robot}} need a bus transport "
                        f"(zenoh); {entry.transport} links one peer to another",
                        "set transport: zenoh on this entry, or write the robot's name")
        if entry.framing is Framing.ROSGATE and not entry.remote.startswith("/"):
            raise error(f"{key}.remote", f"'{entry.remote}' is not a valid ROS name (keys are "
                        f"for bus transports; {entry.transport} is not one)",
                        "use letters, digits and '_' in parts separated by single '/'")
        if cfg.role is Role.PEER:
            if entry.port is None:
                raise error(f"{key}.port", f"peer role: each {kind} needs its own port",
                            f"add port: <1..65535> to this entry (only bus {kind}s, such as "
                            "zenoh's, have none)")
            if cfg.peer is None:
                raise cfg.error("bridge.peer", "missing required key 'peer'",
                                f"add peer: <far host>, the address of the other side "
                                f"({key} is on {entry.transport}, a point-to-point link)")
        if (cfg.role is Role.CLIENT and isinstance(transport, StreamTransport)
                and entry.port is None and entry.transport != cfg.main_line):
            raise error(f"{key}.port", f"a {kind} on {entry.transport} needs a port of its own "
                        f"(only {cfg.main_line} {kind}s ride the main line)", "add port: <number>")

    def _addresses(self, transport: Transport, entry: TopicConfig | ServiceConfig, key: str,
                   error: ErrorMaker) -> tuple[Address, Address]:
        """(the entry's address, the local address a peer sends from), from the bridge's hosts
        and the entry's port, as its transport accepts them (an RFCOMM channel is not any port).

        Client and server: the server's host and the entry's port (default: the main port).
        Peer: a receiving entry listens at ``listen:port``, a transmitting one sends to
        ``peer:port`` from ``listen`` (any port)."""
        cfg = self.config
        if cfg.role is Role.PEER:
            listen = cfg.listen or ANY_IP
            receive = entry.direction is Direction.RECEIVE
            host = listen if receive else cfg.peer
            where = "bridge.listen" if receive else "bridge.peer"
            local = (listen, 0)
            if not receive and isinstance(transport, DatagramTransport):  # a sender binds too
                local = self._check(transport, local, "bridge.listen", error,
                                    f"set bridge.listen to this side's {entry.transport} address")
        else:
            assert self.main_address is not None
            host, where = self.main_address[0], "bridge.server"
            local = ("::" if ":" in host else ANY_IP, 0)
        port = entry.port or (self.main_address[1] if self.main_address else 0)
        fix = f"this {_kind(entry)}'s {entry.transport} address is {where} with port {port}"
        if where == "bridge.listen" and "bridge.listen" not in cfg.lines:  # 0.0.0.0: IP only
            fix = f"set bridge.listen to this side's {entry.transport} address"
        return self._check(transport, (host or "", port), f"{key}.port" if entry.port else where,
                           error, fix), local

    @staticmethod
    def _check(transport: Transport, address: Address, key: str, error: ErrorMaker,
               fix: str) -> Address:
        try:
            return transport.check_address(address)
        except ValueError as exc:
            raise error(key, str(exc), fix) from None

    def _check_shared_ports(self, topics: list[TopicSpec]) -> None:
        """Topics that share a receiving port must be told apart on it."""
        by_port: dict[tuple[str, int | None], list[TopicSpec]] = {}
        topics = [p for p in topics if p.key is None]  # a bus tells topics apart by key
        for p in topics:
            if p.config.direction is Direction.RECEIVE:
                by_port.setdefault((p.config.transport, p.config.port), []).append(p)
        for group in by_port.values():
            bare = [p for p in group if p.config.framing is Framing.NONE]
            if bare and len(bare) != len(group):
                raise self.config.error(f"topics[{bare[0].index}].framing",
                                        "topics on one port must all use the same framing")
            if len(bare) > 1 and not all(p.codec_cls.messagepack for p in bare):
                p = next(p for p in bare if not p.codec_cls.messagepack)
                raise self.config.error(
                    f"topics[{p.index}].port", f"codec {p.config.codec} does not name its frames, "
                    "so with framing: none this topic needs a port of its own",
                    "give each such topic its own port, or use codec msgpack")
        if self.config.role is Role.PEER:
            seen: dict[int, TopicSpec] = {}
            for p in topics:
                t = p.config
                for name in ({t.topic, t.remote} if t.direction is Direction.RECEIVE
                             else {t.remote}):
                    other = seen.setdefault(topic_id_for(name), p)
                    if other is not p and other.config.direction == t.direction:
                        raise self.config.error(
                            f"topics[{p.index}].remote",
                            f"link name {name!r} collides with topics[{other.index}]",
                            "rename one of them (remote: ...)")


def _kind(entry: TopicConfig | ServiceConfig) -> str:
    return "topic" if isinstance(entry, TopicConfig) else "service"
