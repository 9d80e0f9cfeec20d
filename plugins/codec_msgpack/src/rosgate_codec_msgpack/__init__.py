"""rosgate codec ``msgpack``: a ROS message as a MessagePack map, for peers without ROS.

This is the wire format of the CVRA MessagePack bridge: a microcontroller with a small
MessagePack library reads and writes it without knowing anything about ROS or CDR.

Wire mapping: the tree mapping of :mod:`rosgate.message_tree` (shared with the ``cbor``
codec), in MessagePack terms:

=================================  ===========================================================
ROS                                MessagePack
=================================  ===========================================================
message (nested ones too)          map: field name as in the .msg -> value, in .msg order
bool                               true / false
int8 ... int64, uint8 ... uint64   int (smallest encoding, as any MessagePack packer writes it)
byte                               int in [0, 255]
float32                            float 32 (0xca)
float64                            float 64 (0xcb)
string, wstring                    str (UTF-8)
uint8[], uint8[N], byte[], byte[N] bin (the bytes as they are)
any other T[], T[N], T[<=N]        array of T (float32 elements as float 32)
builtin_interfaces/Time, Duration  nothing special: {"sec": ..., "nanosec": ...}
=================================  ===========================================================

Decoding is strict, because the bytes come from the network: anything but exactly one
MessagePack object, a map key that is not a str, an ext type (timestamps included), or a tree
that does not fit the message (see :mod:`rosgate.message_tree`) is a :class:`rosgate.CodecError`
naming the field by its dotted path (``pose.position.w``, ``points[3].x``). Nothing is longer
than the input, and the parser builds at most one array or map per 8 bytes of it
(:func:`rosgate.message_tree.container_budget`): 4 MB of empty maps is refused, not 277 MB.

Framing ``none`` (one datagram per message, several topics on one port): the datagram is the
topic's name as a MessagePack str immediately followed by the map, as the CVRA bridge sends it.
The core writes and reads the name (``messagepack = True`` says it may); this codec only sees
the map.

Options: none.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import msgpack

import rosgate
from rosgate.message_tree import BUDGET_FROM, ContainerBudget, TreeCodec, WireFormat

_packb = msgpack.packb


def _header(small: int, small_count: int, codes: tuple[int, ...]) -> Callable[[int], bytes]:
    """A MessagePack container header: fix form below ``small_count``, then 8/16/32-bit lengths
    under ``codes`` (a code of 0: no such width)."""
    def header(length: int) -> bytes:
        if length < small_count:
            return bytes((small | length,))
        for code, width in zip(codes, (1, 2, 4), strict=True):
            if code and length < 1 << (8 * width):
                return bytes((code,)) + length.to_bytes(width, "big")
        raise ValueError(f"{length} elements do not fit a MessagePack header")
    return header


MESSAGEPACK = WireFormat(
    name="MessagePack", pack=_packb, float32_tag=0xCA, float64_tag=0xCB,
    array_header=_header(0x90, 16, (0, 0xDC, 0xDD)),
    map_header=_header(0x80, 16, (0, 0xDE, 0xDF)),
    bytes_header=_header(0, 0, (0xC4, 0xC5, 0xC6)),
)


def _unpack_limits(size: int) -> dict[str, int]:
    # nothing in the input is longer than the input: a forged length cannot make us allocate;
    # ext types (timestamps included) mean nothing in a ROS message
    return {"max_bin_len": size, "max_str_len": size, "max_array_len": size,
            "max_map_len": size, "max_ext_len": 0}


# What msgpack raises for bytes it cannot read: ExtraData, FormatError, StackError and
# UnicodeDecodeError are ValueErrors, OutOfData and BufferFull UnpackExceptions, and TypeError
# comes for something that is not bytes at all.
_UNREADABLE = (ValueError, TypeError, msgpack.UnpackException)


class MsgpackCodec(TreeCodec):
    """ROS messages as MessagePack maps; the module documentation has the mapping."""

    name = "msgpack"
    messagepack = True
    wire = MESSAGEPACK

    def parse(self, data: bytes) -> Any:
        size = len(data)
        hooks: dict[str, Any] = {}
        if size > BUDGET_FROM:
            budget = ContainerBudget(size)
            hooks = {"object_hook": budget, "list_hook": budget}
        try:
            return msgpack.unpackb(data, raw=False, strict_map_key=True, **_unpack_limits(size),
                                   **hooks)
        except _UNREADABLE as exc:
            reason = str(exc) or type(exc).__name__
            raise rosgate.CodecError(
                f"{self.tree.name}: not one MessagePack object: {reason}") from None


@rosgate.hookimpl
def rosgate_codecs(register: Callable[[type[rosgate.Codec]], None]) -> None:
    register(MsgpackCodec)
