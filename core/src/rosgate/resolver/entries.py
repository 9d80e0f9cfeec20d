"""An entry of the file — topic, service, action — checked against what is installed and made a
:class:`~rosgate.spec.RouteSpec`: its plugins, its type, how its link carries it (reliability,
priority, recovery), where its frames go (:mod:`.places`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

from .. import actions
from ..bus import BusTransport
from ..codec import Codec
from ..config import (
    NO_PLUGIN,
    PRIORITIES,
    ActionConfig,
    BridgeConfig,
    Framing,
    Role,
    ServiceConfig,
    TopicConfig,
)
from ..errors import OptionError
from ..packetizer import SMALL_FRAME, Packetizer, own_packetizer
from ..plugins import Plugins
from ..rostypes import TypeNotFound, is_reliable, resolve_type
from ..service_framing import ServiceFraming
from ..spec import Delivery, ServiceSpec, TopicSpec
from ..transport import DatagramTransport, StreamTransport, Transport
from ..wire.framing import DEFAULT_MAX_MESSAGE
from .made import ErrorMaker
from .places import Placer

log = logging.getLogger("rosgate")

#: the packetizer that repairs a reliable topic on a datagram link when it sets no recovery:
#: selective repeat costs a round trip per loss and bandwidth only for what was lost, keeps the
#: topic on the link the file chose (no head-of-line wait behind other topics, as on the main
#: line's stream) and is the far side's to answer without a setting
RELIABLE_RECOVERY = "retransmit"


@dataclass
class PreparedAction:
    """An action as the five entries it is made of (rosgate.actions), each prepared."""

    config: ActionConfig
    parts: list[TopicSpec | ServiceSpec]



class EntryResolver(Placer):
    """Resolves a bridge's entries, one by one."""

    def __init__(self, config: BridgeConfig, plugins: Plugins):
        super().__init__(config, plugins)
        #: what entries give up, said once each (a reliable topic carried unrepaired)
        self.cautions: list[str] = []

    def topic(self, topic: TopicConfig, index: int, section: str,
              error: ErrorMaker | None = None) -> TopicSpec:
        error = error or self.config.error
        key = f"{section}[{index}]"
        transport, common = self._entry(topic, index, key, error)
        if topic.framing is Framing.NONE and isinstance(transport, StreamTransport):
            raise error(f"{key}.framing",
                        "framing: none needs a datagram transport (udp, can, ...)",
                        "use framing: rosgate on stream links")
        delivery = self._delivery(topic, key, transport, error)
        compression = None if topic.compression == NO_PLUGIN else self._made(
            "transform", topic.compression, f"{key}.compression", error, DEFAULT_MAX_MESSAGE,
            own=topic.compression_options)
        return TopicSpec(**common, **self._where(topic, key, transport, error),
                         delivery=delivery, compression=compression,
                         transforms=self.transform_for)

    def _entry(self, entry: TopicConfig | ServiceConfig, index: int, key: str,
               error: ErrorMaker) -> tuple[Transport, dict[str, Any]]:
        """An entry's transport, and what its spec holds of every plugin and of its type, each
        checked: its codec's options fit the type (a service's Request and Response)."""
        transport = self.transport(entry.transport, f"{key}.transport", error)
        if isinstance(transport, DatagramTransport) and entry.framing is Framing.ROSGATE:
            name = own_packetizer(transport.max_frame)  # a link of small frames needs a plugin's
            if self.plugins.get("packetizer", name) is None:
                message, fix = self.plugins.explain_missing("packetizer", name, False)
                raise error(f"{key}.transport", f"{transport.name} carries packets of "
                            f"{transport.max_frame} bytes, which its links cut with the "
                            f"packetizer {name!r}: {message}", fix)
        # the codec's options are parsed once; the router makes an instance per route
        codec_cls: type[Codec] = self.plugin("codec", entry.codec, f"{key}.codec", error).cls
        codec_options = _microcontroller(codec_cls, self._plugin_options(
            codec_cls, entry.codec, {}, f"{key}.codec", error), entry)
        cipher_cls, cipher = self._entry_cipher(entry.cipher, f"{key}.cipher", error,
                                                isinstance(transport, BusTransport))
        try:
            interface: Any = resolve_type(entry.type)
        except TypeNotFound as exc:
            raise error(f"{key}.type", str(exc)) from None
        topic = isinstance(entry, TopicConfig)
        try:
            for part in (interface,) if topic else (interface.Request, interface.Response):
                codec_cls(part, codec_options)
        except OptionError as exc:
            raise self.option_error(entry.codec, exc, f"{key}.codec", error) from None
        return transport, {"config": entry, "msg_type" if topic else "srv_type": interface,
                           "codec_cls": codec_cls, "codec_options": codec_options,
                           "transport": transport, "cipher": cipher, "cipher_cls": cipher_cls,
                           "index": index}

    def _delivery(self, topic: TopicConfig, key: str, transport: Transport,
                  error: ErrorMaker) -> Delivery:
        """Recovery is for datagram links, latest_only for the links rosgate schedules (a bus
        paces and drops by itself)."""
        bus = isinstance(transport, BusTransport)
        if topic.recovery not in (None, NO_PLUGIN) and (isinstance(transport, StreamTransport)
                                                         or bus):
            what = "a bus" if bus else "a stream"
            raise error(f"{key}.recovery", f"recovery: {topic.recovery} is for datagram links "
                        f"(udp): {topic.transport} is {what}, which delivers whole and in order "
                        "by itself", "remove recovery: from this entry")
        if topic.latest_only is not None and bus:
            raise error(f"{key}.latest_only", f"latest_only applies to links rosgate schedules; "
                        f"{topic.transport} is a bus, which drops best-effort samples itself "
                        "when it is congested", "remove latest_only: from this entry")
        reliable, priority = is_reliable(topic.qos), topic.priority or PRIORITIES["data"]
        if bus:
            return Delivery(reliable=reliable, priority=priority)
        packetizer: type[Packetizer] | None = None
        options = None
        recovery = self._recovery(topic, key, reliable, transport)
        if recovery != NO_PLUGIN:
            packetizer = self.plugin("packetizer", recovery, f"{key}.recovery", error).cls
            if packetizer.cuts_every_frame:
                raise error(f"{key}.recovery", f"{recovery} is what links of small frames "
                            "cut every frame with, by themselves: it recovers nothing",
                            "remove recovery: from this entry, or pick fec or retransmit")
            small = transport.max_frame if isinstance(transport, DatagramTransport) else 0
            if 0 < small < SMALL_FRAME:  # its own packetizer cuts every frame: none else would
                raise error(f"{key}.recovery", f"{topic.transport} carries frames of {small} "
                            "bytes, which it cuts into compact pieces with no room for "
                            f"{recovery}'s numbers: it would recover nothing",
                            f"give {topic.transport} a max_frame of {SMALL_FRAME} or more, or "
                            "remove recovery: from this entry")
            options = self._plugin_options(packetizer, recovery, topic.recovery_options,
                                           f"{key}.recovery", error)
        latest_only = not reliable if topic.latest_only is None else topic.latest_only
        return Delivery(reliable=reliable, priority=priority, latest_only=latest_only,
                        max_delay=topic.max_delay, packetizer=packetizer,
                        packetizer_options=options, whole=topic.framing is Framing.NONE)

    def _recovery(self, topic: TopicConfig, key: str, reliable: bool,
                  transport: Transport) -> str:
        """A datagram topic's recovery: its own, else by its QoS (a reliable topic is repaired,
        in order, by :data:`RELIABLE_RECOVERY`; a best-effort one stays fresh). What a reliable
        topic gives up without it is said (:attr:`cautions`)."""
        # a link of small frames (CAN) repairs in its hardware, and has no room for the header
        repairable = (isinstance(transport, DatagramTransport) and topic.framing is Framing.ROSGATE
                      and transport.max_frame >= SMALL_FRAME)
        if not (repairable and reliable):
            return topic.recovery or NO_PLUGIN
        name = f"{topic.topic} ({key})"
        if topic.recovery == NO_PLUGIN:
            self.caution(f"{name}: reliable QoS on {topic.transport} with recovery: none: a "
                         "datagram lost on the way loses its message (counted as lost on the "
                         "way by the receiver), and messages may be published out of order. "
                         "Leave recovery: out to have them repaired (retransmit)")
        if topic.recovery is not None:
            return topic.recovery
        if self.plugins.get("packetizer", RELIABLE_RECOVERY) is None:
            message, fix = self.plugins.explain_missing("packetizer", RELIABLE_RECOVERY, False)
            self.caution(f"{name}: reliable QoS on {topic.transport}, where the packetizer "
                         f"{RELIABLE_RECOVERY!r} would repair what is lost on the way; it is not "
                         f"here ({message}), so a lost datagram loses its message. {fix}; or "
                         "set recovery: none to accept it")
            return NO_PLUGIN
        return RELIABLE_RECOVERY

    def caution(self, text: str) -> None:
        """Say once, as a warning, what an entry gives up (``rosgate check`` and ``run``)."""
        if text not in self.cautions:
            self.cautions.append(text)
            log.warning("%s", text)

    def service(self, service: ServiceConfig, index: int, section: str,
                error: ErrorMaker | None = None) -> ServiceSpec:
        error = error or self.config.error
        key = f"{section}[{index}]"
        transport, common = self._entry(service, index, key, error)
        service_framing: type[ServiceFraming] | None = None
        if service.framing is not Framing.ROSGATE:  # a microcontroller's calls: by a plugin
            service_framing = self.plugin("service_framing", service.framing.value,
                                          f"{key}.framing", error).cls
            if self.config.role is not Role.PEER:
                raise error(f"{key}.framing", f"framing {service.framing} is for microcontroller "
                            "peers, which have no main line", "use role: peer for this bridge")
            on_a_line = isinstance(transport, DatagramTransport) and transport.one_line
            if not isinstance(transport, StreamTransport) and not (
                    on_a_line and service_framing.on_a_line):
                raise error(f"{key}.transport", f"framing {service.framing} needs a stream "
                            "transport (one connection per call)", "use transport: tcp")
            if not common["codec_cls"].messagepack:
                raise error(f"{key}.codec", f"codec {service.codec} does not put the service's "
                            "name on the wire (it does not write MessagePack)",
                            "use codec: msgpack")
        return ServiceSpec(**common, **self._where(service, key, transport, error),
                           service_framing=service_framing)

    def action(self, action: ActionConfig, index: int, section: str,
               error: ErrorMaker | None = None) -> PreparedAction:
        """An action's five entries, prepared as topics and services are; a mistake is
        located at the action's keys."""
        error = error or self.config.error
        key = f"{section}[{index}]"
        try:
            resolve_type(action.type)
        except TypeNotFound as exc:
            raise error(f"{key}.type", str(exc)) from None
        bus = isinstance(self.transport(action.transport, f"{key}.transport", error),
                         BusTransport)
        if self.config.role is Role.PEER and action.port is None and not bus:
            raise error(f"{key}.port", "peer role: an action needs a port (its calls use it, "
                        "its feedback and status the next one)", "add port: <1..65534>")
        return PreparedAction(action, [
            self.topic(part, index, section, error) if isinstance(part, TopicConfig)
            else self.service(part, index, section, error) for part in actions.parts(action)])


def _microcontroller(codec_cls: type[Codec], options: Any,
                     entry: TopicConfig | ServiceConfig) -> Any:
    """A MessagePack codec on a microcontroller entry writes as the entry's ``args`` and
    ``floats`` say, where its options declare them (the msgpack codec's do)."""
    if not (entry.framing.bare and codec_cls.messagepack and dataclasses.is_dataclass(options)
            and not isinstance(options, type)):
        return options
    declared = {f.name for f in dataclasses.fields(options)}
    wanted = {"args": entry.args, "floats": entry.floats}
    return dataclasses.replace(options, **{k: v for k, v in wanted.items() if k in declared})
