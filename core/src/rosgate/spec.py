"""What a route needs, decided once by the resolver and never looked up again: a frozen
:class:`RouteSpec` per entry (plugins found, interface imported, addresses checked), and the
:class:`Delivery` a link reads of every frame's sender.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from .cipher import Cipher
from .codec import Codec
from .config import PRIORITIES, ServiceConfig, TopicConfig
from .packetizer import Packetizer
from .service_framing import ServiceFraming
from .transform import Transform
from .transport import Address, Transport


@dataclass(frozen=True, slots=True)
class Delivery:
    """How a link carries the frames of one sender."""

    #: frames wait out a stream link's loss (reliable QoS); best-effort frames that waited
    #: longer than the link's ``max_delay`` are dropped (``too_late``)
    reliable: bool = False
    #: the scheduler's class: 0 control, 1 (real time) .. 7 (background)
    priority: int = PRIORITIES["data"]
    #: a frame not yet started is replaced by the sender's next one (``superseded``)
    latest_only: bool = False
    #: seconds a frame may wait to start (None: the link's, for best-effort senders)
    max_delay: float | None = None
    #: the packetizer that cuts every frame, and the topic's options for it (None: the link's
    #: own: whole when it fits, else ``fragments``)
    packetizer: type[Packetizer] | None = None
    packetizer_options: Any = None
    #: ``framing: none``: every frame is a whole datagram, never cut
    whole: bool = False

    @property
    def real_time(self) -> bool:
        """Priority ``real_time``: a transmitting topic's subscription is taken on a thread of
        its own (:class:`rosgate.ros.RosNode`), not behind the other topics' messages."""
        return self.priority == PRIORITIES["real_time"]


#: hellos, pings, handshakes: above every topic's class, never waiting out a link's loss
CONTROL = Delivery(priority=0)


@dataclass(frozen=True, slots=True, kw_only=True)
class RouteSpec:
    """An entry, resolved: what the wiring needs to build its link side and its route."""

    config: TopicConfig | ServiceConfig
    codec_cls: type[Codec]
    codec_options: Any
    transport: Transport
    cipher: Cipher | None  # built from the file's key; None in a session (keyed from it)
    index: int  # position in the file (or in the client's list), for error messages
    address: Address  # the far side; a peer's receiving entry: where to listen
    local: Address  # peer role, datagram transmit: where to send from
    delivery: Delivery = Delivery()
    key: str | None = None  # on a bus: the key (a template with placeholders), else None
    cipher_cls: type[Cipher] | None = None
    #: "topic" or "service": how logs, errors and key labels name it
    kind: ClassVar[str]

    @property
    def name(self) -> str:
        """The entry's ROS name on this side."""
        return self.config.topic if isinstance(self.config, TopicConfig) else self.config.service


@dataclass(frozen=True, slots=True, kw_only=True)
class TopicSpec(RouteSpec):
    """A topic entry, resolved: its entry (``config``), the ROS message class (``msg_type``),
    codec, transport, cipher, delivery and, on a bus, its ``key``; what a bus role makes its
    routes from."""

    kind = "topic"
    config: TopicConfig
    msg_type: type
    #: compression: the transform a transmitting topic applies (None: none)
    compression: Transform | None = None
    #: a receiving topic's transform of each wire id, whatever its own entry says
    transforms: Callable[[int], Transform | None] = field(default=lambda wire_id: None)


@dataclass(frozen=True, slots=True, kw_only=True)
class ServiceSpec(RouteSpec):
    """A service entry, resolved as a :class:`TopicSpec` is, with the ROS service class
    (``srv_type``) and the service framing that makes its calls, if not rosgate's."""

    kind = "service"
    config: ServiceConfig
    srv_type: Any  # a ROS service class: Request and Response inside
    #: the plugin that makes its calls when ``framing`` is not ``rosgate`` (a microcontroller's)
    service_framing: type[ServiceFraming] | None = None
