"""bringup.yaml's keys, each declared once: type, default, bounds or choices, one line of doc and
an example for an error's fix. The loader reads a file against them (and adds the rules that tie
keys together); docs/configuration.md's reference is generated from them (``tools/docgen``).
Here the file's top level and ``bridge:``; an entry's keys are :mod:`.entries`', ``clients:``
:mod:`.clients`'."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..options import option
from . import kinds
from .clients import ClientPolicy
from .entries import (
    CIPHER_DEFAULT,
    CODEC_DEFAULT,
    TRANSPORT_DEFAULT,
    ActionConfig,
    ServiceConfig,
    TopicConfig,
)
from .kinds import Key, read
from .patterns import DENY_DEFAULT, deny_list
from .source import line_of


class Role(StrEnum):
    CLIENT = "client"
    SERVER = "server"
    PEER = "peer"


SESSION_CIPHER_DEFAULT = "aead"   # the default cipher inside an authenticated session
LISTEN_DEFAULT = "0.0.0.0"
PEER_TIMEOUT_HEARTBEATS = 3       # default bridge.peer_timeout, in heartbeats
RECONNECT_MAX_DEFAULT = 10.0
MAX_DELAY_DEFAULT = 1.0           # seconds a best-effort message may wait in a link's queue


@dataclass(frozen=True)
class LinkConfig:
    """``bridge.links.<transport>``: what this side may put on each link of that transport."""

    transport: str
    bandwidth: float | None = option(None, "bits per second this side sends at most to each "
                                     "destination, packet headers counted; not for a bus",
                                     unset="unlimited", example="20mbit", parse=kinds.bandwidth)
    max_delay: float = option(MAX_DELAY_DEFAULT, "seconds a best-effort message without a "
                              "`max_delay` of its own may wait in the send queue (`too_late`)",
                              above=0, unit="seconds", example="1.0")
    line: int = 0


@dataclass(frozen=True)
class Limits:
    """``bridge.limits``: what a peer may cost this bridge before it is trusted (a client before
    its handshake, a stranger on a port), so that strangers cannot exhaust it."""

    connections: int = option(256, "stream connections held at once, over every listening port "
                              "(each costs two threads); more are closed (`too_many_connections`)",
                              minimum=1, example="256")
    connections_per_source: int = option(16, "of those, from one source address "
                                         "(`too_many_per_source`): a client's main line, its "
                                         "ports and a reconnect fit", minimum=1, example="16")
    handshake_timeout: float = option(5.0, "seconds an accepted connection has to complete its "
                                      "handshake or introduce itself (`handshake_timeout`)",
                                      above=0, unit="seconds", example="5")
    max_frame_before_auth: int = option(64 * 1024, "bytes a frame may have on such a connection "
                                        "until then (`bad_length`)", minimum=1024, unit="bytes",
                                        example="65536")
    idle_timeout: float = option(2.0, "seconds a connection to a microcontroller service port "
                                 "may stay silent (`idle_timeout`)", above=0, unit="seconds",
                                 example="2")
    sessions: int = option(256, "server: client sessions kept at once (connected, or waiting out "
                           "`session_timeout`); a new client past it is refused", minimum=1,
                           example="256")


@dataclass
class Defaults:
    """``bridge.defaults``: for entries that do not say."""

    transport: str = option(TRANSPORT_DEFAULT, "the transport of entries", example="udp")
    codec: str = option(CODEC_DEFAULT, "the codec of entries", example="cdr")
    cipher: str = option(CIPHER_DEFAULT, "the cipher of entries", example="none",
                         unset="`aead` in a client/server session, else `none`")


def _section(section: type, build: bool = True) -> Any:
    """The parse function of a key holding a fixed mapping (``bridge.limits``): the ``section``
    made of it, or (``build`` false) the keys given, for the loader to complete."""

    def parse(key: Key, value: Any) -> Any:
        given = read(key.src, kinds.mapping(key, value), key.path, section)
        return section(**given) if build else given

    parse.section = section  # type: ignore[attr-defined]  # the docs list its keys
    parse.__doc__ = "a mapping"
    return parse


def _links(key: Key, value: Any) -> dict[str, LinkConfig]:
    """per transport: `{udp: {bandwidth: 20mbit}}`"""
    return {name: kinds.item(key.src, f"{key.path}.{name}", given, LinkConfig, "a mapping",
                             f"write it as {name}: {{bandwidth: 20mbit}}", name)
            for name, given in kinds.mapping(key, value).items()}


_links.section = LinkConfig  # type: ignore[attr-defined]


@dataclass
class BridgeConfig:
    """The keys under `bridge:`, all optional but name and role; see [Links that
    fail](real-links.md#links-that-fail) and [Real links](real-links.md):"""

    file: str
    name: str = option(doc="this side's name; a server knows a client by it (`clients:`)",
                       example="robot1", parse=kinds.bridge_name)
    role: Role = option(doc="what this side is", example="client")
    server: str | None = option(None, "client: the server's main line, `host:port` or `[v6]:port` "
                                "(Bluetooth: `AA:BB:CC:DD:EE:FF/5`); server: where it listens",
                                unset="required for client and server", example="127.0.0.1:12000")
    main_line: str = option("tcp", "client, server: the stream transport of the main line and "
                            "handshake", example="tcp")
    peer: str | None = option(None, "peer: the far host, where topics are sent (not needed on a "
                              "bus)", unset="required for point-to-point links",
                              example="192.168.1.20")
    listen: str | None = option(None, "peer: the address this side binds",
                                unset=f"`{LISTEN_DEFAULT}`", example=LISTEN_DEFAULT)
    defaults: dict[str, str] = option({"transport": TRANSPORT_DEFAULT, "codec": CODEC_DEFAULT,
                                       "cipher": CIPHER_DEFAULT},
                                      "`{transport, codec, cipher}` for entries that do not say",
                                      example="{transport: udp, codec: cdr, cipher: none}",
                                      parse=_section(Defaults, build=False))
    stale_after: float = option(15.0, "seconds of silence on a received topic before a warning",
                                above=0, example="15")
    stale_warnings: int = option(5, "warnings per silence (0: none)", minimum=0, example="5")
    heartbeat: float = option(1.0, "seconds between pings on the main line", above=0, example="1.0")
    peer_timeout: float = option(3.0, "seconds of silence on the main line before the far side "
                                 "is declared down; must exceed `heartbeat`", above=0,
                                 unit="seconds", unset="3 × `heartbeat`", example="3.0")
    session_timeout: float = option(60.0, "server: seconds a client that lost its main line "
                                    "keeps its session (routes, ids, queued frames)", above=0,
                                    unit="seconds", example="60")
    reconnect_min: float = option(0.1, "seconds before the first reconnection attempt; then "
                                  "doubling, with jitter", key="reconnect.min", above=0,
                                  unit="seconds", example="0.1")
    reconnect_max: float = option(RECONNECT_MAX_DEFAULT, "seconds between attempts at most",
                                  key="reconnect.max", above=0, unit="seconds", example="10",
                                  unset="`10`, or `min` when larger")
    queue_frames: int = option(1000, "client: the messages reliable topics hold while the server "
                               "is out of reach (and a stream link, or a datagram link whose line "
                               "is gone, a serial device unplugged, while it is down)",
                               key="queue.frames", minimum=0, example="1000")
    queue_bytes: int = option(8 * 1024 * 1024, "and the bytes", key="queue.bytes", minimum=0,
                              example="8388608")
    limits: Limits = option(Limits(), "what a peer may cost before it is trusted",
                            example="{connections: 256, connections_per_source: 16, "
                                    "handshake_timeout: 5}", parse=_section(Limits))
    identity: bytes | None = option(None, "this side's private key file (relative to the file), "
                                    "mode 0600", example="robot1.key", parse=kinds.text,
                                    unset="client, server: required, unless `insecure: true`; "
                                          "peer: optional")
    server_key: bytes | None = option(None, "client: the server's public key (base64, 44 "
                                      "characters)", unset="required with `identity`",
                                      example="<the server's public key, from rosgate keygen "
                                              "identity>", parse=kinds.text)
    handshake_port: int | None = option(None, "peer with `identity`: the port of the "
                                        "handshake line (on `handshake_line`)", minimum=1,
                                        maximum=65535, unset="—",
                                        example="12100")
    handshake_line: str = option("tcp", "peer with `identity`: the transport of the handshake "
                                 "line: a stream (tcp), or the peers' datagram link when it "
                                 "is all they share (serial), which then carries it with "
                                 "repetitions", example="serial")
    insecure: bool = option(False, "`true` accepts links anyone can write to (no handshake, no "
                            "keyed cipher, a bus without mutual TLS on every link), named in a "
                            "warning on every `run` and `check`; the file's one such key",
                            example="true")
    rekey: float = option(120.0, "server (or responding peer): seconds a session key generation "
                          "lasts", minimum=1, unit="seconds", example="120")
    allow: tuple[Any, ...] = option((), "peer: the only addresses or networks frames and calls "
                                    "are taken from; others are counted `not_allowed`",
                                    unset="datagram and stream ports: `bridge.peer` only; "
                                          "microcontroller service ports: anyone",
                                    example="[192.168.0.20, 10.1.0.0/24]", parse=kinds.networks)
    peer_key: str | None = option(None, "peer with `identity`: the other peer's public key",
                                  unset="—", example="<the other peer's public key>",
                                  parse=kinds.text)
    clients: dict[str, ClientPolicy] = field(default_factory=dict)  # server: who may connect
    fleet_timeout: float = option(30.0, "seconds after a robot's liveliness token went before "
                                  "its fleet routes are dropped (see [Fleets](fleets.md))",
                                  above=0, unit="seconds", example="30")
    links: dict[str, LinkConfig] = option({}, "per transport, what this side may put on each link",
                                          example="{udp: {bandwidth: 20mbit}}", parse=_links)
    diagnostics: bool = option(True, "publish `diagnostic_msgs/DiagnosticArray` on `/diagnostics` "
                               "once a second (see [operators.md](operators.md))", example="false")
    metrics: str | None = option(None, "`host:port` of a Prometheus endpoint (the "
                                 "`rosgate-metrics-prometheus` monitor)", unset="none",
                                 example="127.0.0.1:9108", parse=kinds.text)
    metrics_public: bool = option(False, "let `metrics` bind an address that is not loopback",
                                  example="true")
    deny: tuple[str, ...] = option(DENY_DEFAULT, "names (or patterns) no pattern entry bridges; "
                                   "a name listed as an entry is bridged all the same",
                                   unset="`[" + ", ".join(DENY_DEFAULT) + "]`",
                                   example="[/rosout, /parameter_events, /robot1/debug/**]",
                                   parse=deny_list)
    pattern_grace: float = option(10.0, "seconds a name a pattern entry found keeps its route "
                                  "after its last publisher went; then the route is removed on "
                                  "both sides", above=0, unit="seconds", example="10")
    plugins: dict[str, dict] = field(default_factory=dict)
    topics: list[TopicConfig] = field(default_factory=list)
    services: list[ServiceConfig] = field(default_factory=list)
    actions: list[ActionConfig] = field(default_factory=list)
    lines: dict[str, int] = field(default_factory=dict)
    base_dir: Path = field(default_factory=Path.cwd)

    def error(self, key: str, message: str, fix: str | None = None) -> ConfigError:
        """A ConfigError at the line of dotted key `key` (or of its nearest parent)."""
        return ConfigError(message, file=self.file, line=line_of(self.lines, key), key=key,
                           fix=fix)

    @property
    def secure(self) -> bool:
        """With identities: every link of a session is authenticated."""
        return self.identity is not None


@dataclass
class File:
    """The file's top level; the loader reads each section."""

    bridge: dict = option(doc="this side: its name, role and links", example="{name: robot1, "
                          "role: client, server: 127.0.0.1:12000}")
    plugins: dict = option({}, "each plugin's options, by its name",
                           example="{fernet: {key_file: secret.key}}")
    topics: list = option([], "the topics to bridge", example="- topic: /chatter")
    services: list = option([], "the services to bridge", example="- service: /mcu/ping")
    actions: list = option([], "the actions to bridge", example="- action: /navigate_to_pose")
    clients: dict = option({}, "server: the clients it accepts",
                           example="{robot1: {key: <public key>, topics: [{name: /robot1/**, "
                                   "direction: both}]}}")
