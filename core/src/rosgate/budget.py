"""The budget arithmetic ``rosgate check`` shows: for each link with a ``bandwidth``
(``bridge.links``), what this side's topics with a ``max_rate`` would put on it — each message's
size on the wire (envelope, cipher, what its packetizer adds — fragment headers, FEC repair
fragments —, the transport's packet headers) times its rate — against the bandwidth.

A message's size is ``typical_size`` when the entry gives one, else the CDR size of a default
message when its type has no field of variable length (a Twist: exact), else unknown (an
Image: give ``typical_size``). Compression is not counted (what it saves depends on the
data); nor are retransmissions (they depend on the losses).
"""

from __future__ import annotations

import math
from typing import Any

from .builtin import Fragments
from .config import Direction, Framing
from .packetizer import Packetizer, own_packetizer
from .plugins import installed
from .resolver.plan import Plan
from .rostypes import resolve_type
from .spec import TopicSpec
from .transport import DatagramTransport, line_budget
from .wire import envelope, framing

#: tc-style: the bits of a link in the units people write them in
UNITS = ((1e9, "Gbit/s"), (1e6, "Mbit/s"), (1e3, "kbit/s"), (1, "bit/s"))


def rate_text(bits: float) -> str:
    scale, unit = next((scale, unit) for scale, unit in UNITS if bits >= scale or scale == 1)
    return f"{bits / scale:,{'.3g' if bits < 10 * scale else '.1f'}} {unit}"


def fixed_size(msg_type: Any) -> int | None:
    """The CDR size of every message of ``msg_type`` when no field varies in length, else
    None."""
    if not _fixed(msg_type):
        return None
    from rclpy.serialization import serialize_message

    return len(serialize_message(msg_type()))


def _fixed(msg_type: Any) -> bool:
    for kind in msg_type.get_fields_and_field_types().values():
        if "sequence<" in kind or kind.startswith("string") or kind.startswith("wstring"):
            return False
        base = kind.split("[")[0]
        if "/" in base:  # a nested message: pkg/Type
            package, _, name = base.partition("/")
            if not _fixed(resolve_type(f"{package}/msg/{name}")):
                return False
    return True


def cipher_overhead(p: TopicSpec) -> int:
    """Bytes a topic's cipher adds to a frame (its session's cipher when there is no static
    one)."""
    cipher = p.cipher
    if cipher is None and p.cipher_cls is not None and p.cipher_cls.session_key_size:
        cipher = p.cipher_cls.from_secret(bytes(p.cipher_cls.session_key_size))
    if cipher is None:
        return 0
    header = envelope.pack(0, 1, 1, 1, 0)
    return len(cipher.seal(header, bytes(100))) - 100


def on_the_wire(frame: int, p: TopicSpec) -> tuple[int, int]:
    """(bytes, packets) of one frame of ``frame`` bytes on the topic's link."""
    transport = p.transport
    if not isinstance(transport, DatagramTransport):  # a stream: budgets refuse buses
        chunks = 1 if frame <= framing.CHUNK else math.ceil(frame / framing.CHUNK)
        return frame + (4 if chunks == 1 else 8 * chunks), chunks
    limit, overhead = transport.max_frame, transport.packet_overhead
    found = installed().get("packetizer", own_packetizer(limit))  # the resolver checked it
    own: type[Packetizer] = found.cls if found is not None else Fragments
    packetizer, options = p.delivery.packetizer, p.delivery.packetizer_options
    if own.cuts_every_frame or packetizer is None:  # the link's own packetizer
        if frame <= limit and not own.cuts_every_frame:
            return frame + overhead, 1
        packetizer = own
    size, packets = packetizer.cost(frame, limit, options)
    return size + packets * overhead, packets


def report(plan: Plan) -> list[str]:
    """The lines ``rosgate check`` prints: one block per budgeted transport this side uses."""
    lines: list[str] = []
    transports = {p.transport.name: p.transport for p in plan.topics}
    for name in sorted(plan.config.links.keys() | transports.keys()):
        link = line_budget(plan.config.links, transports[name]) if name in transports \
            else plan.config.links[name]
        topics = [p for p in plan.topics
                  if p.config.transport == name and p.config.direction is Direction.TRANSMIT]
        if link is None or link.bandwidth is None or not topics:
            continue
        lines.append(f"budget of {name}: {rate_text(link.bandwidth)} per peer"
                     + ("" if name in plan.config.links and plan.config.links[name].bandwidth
                        else " (the link's own)"))
        width = max(len(p.config.topic) for p in topics)
        total = 0.0
        for p in topics:
            t = p.config
            head = f"  {t.topic:<{width}}  "
            size = t.typical_size or fixed_size(p.msg_type)
            if size is None:
                lines.append(f"{head}not counted ({t.type} varies in size: give typical_size)")
                continue
            frame = size if t.framing is not Framing.ROSGATE else \
                envelope.SIZE + cipher_overhead(p) + size
            wire, packets = on_the_wire(frame, p)
            if t.max_rate is None:
                lines.append(f"{head}{size:,} B a message, {wire:,} B on the wire; not counted "
                             "(no max_rate: as often as it is published)")
                continue
            bits = t.max_rate * wire * 8
            total += bits
            alone = "; cannot fit: more than the whole budget by itself" \
                if bits > link.bandwidth else ""
            lines.append(f"{head}{t.max_rate:g} Hz x {size:,} B = {wire:,} B on the wire "
                         f"({packets:,} packet{'s' if packets != 1 else ''}) -> {rate_text(bits)}"
                         f"{alone}")
        share = total / link.bandwidth
        verdict = "fits" if share <= 1 else "over budget: latest_only topics send less often, " \
            "others wait in the queue (reliable) or are dropped late (best effort)"
        lines.append(f"  total {rate_text(total)} of {rate_text(link.bandwidth)} "
                     f"({100 * share:.1f} %): {verdict}")
    return lines
