"""rosgate codec ``cbor``: a ROS message as a CBOR map (RFC 8949), for peers without ROS.

CBOR is MessagePack's standardised cousin (an IETF RFC, with libraries for every language and
for microcontrollers: TinyCBOR, QCBOR, nanocbor). The mapping is the one the ``msgpack`` codec
uses, shared through :mod:`rosgate.message_tree`; in CBOR terms:

=================================  ===========================================================
ROS                                CBOR
=================================  ===========================================================
message (nested ones too)          map: text key = field name as in the .msg, in .msg order
bool                               true / false (0xf5 / 0xf4)
int8 ... int64, uint8 ... uint64   unsigned or negative integer, smallest encoding
byte                               unsigned integer in [0, 255]
float32                            single-precision float (0xfa)
float64                            double-precision float (0xfb)
string, wstring                    text string (UTF-8)
uint8[], uint8[N], byte[], byte[N] byte string (the bytes as they are)
any other T[], T[N], T[<=N]        array of T (float32 elements as single-precision floats)
builtin_interfaces/Time, Duration  nothing special: {"sec": ..., "nanosec": ...}
=================================  ===========================================================

Writing uses definite lengths only. Reading is strict, because the bytes come from the network:
anything but exactly one CBOR data item is refused (trailing bytes too), as are map keys that
are not text or byte strings, duplicate keys, nesting deeper than 64, and any tree that does
not fit the message (an unknown field, a value of the wrong type or range, a fixed array of
the wrong length, a bounded sequence or string over its bound, a tagged value such as a
date where a number belongs) — each a :class:`rosgate.CodecError` naming the field by its
dotted path (``pose.position.w``). Fields left out keep the message's defaults; an integer
is accepted where a float is expected (half-precision floats too); a boolean is never a number.

Options: none. Framing ``none`` carries the map alone (one topic per port).
"""

from __future__ import annotations

import io
from typing import Any, Callable

import cbor2

import rosgate
from rosgate.message_tree import TreeCodec, WireFormat


def _header(major: int) -> Callable[[int], bytes]:
    """The head of a CBOR data item of major type ``major`` and argument ``length``."""
    base = major << 5

    def header(length: int) -> bytes:
        if length < 24:
            return bytes((base | length,))
        for extra, width in ((24, 1), (25, 2), (26, 4), (27, 8)):
            if length < 1 << (8 * width):
                return bytes((base | extra,)) + length.to_bytes(width, "big")
        raise ValueError(f"{length} does not fit a CBOR head")
    return header


CBOR = WireFormat(
    name="CBOR", pack=cbor2.dumps, float32_tag=0xFA, float64_tag=0xFB,
    bytes_header=_header(2), array_header=_header(4), map_header=_header(5),
    bytes_word="a byte string", str_word="text", nil_word="null",
)

MAX_DEPTH = 64  # far deeper than any ROS message; bounds what a hostile peer can make us recurse


class CborCodec(TreeCodec):
    """ROS messages as CBOR maps; the module documentation has the mapping."""

    name = "cbor"
    wire = CBOR

    def parse(self, data: bytes) -> Any:
        stream = io.BytesIO(data)
        try:
            tree = cbor2.CBORDecoder(stream, max_depth=MAX_DEPTH, allow_duplicate_keys=False,
                                     strict_hashable_types=True).decode()
        except cbor2.CBORDecodeError as exc:  # every unreadable input, tags' contents included
            raise rosgate.CodecError(f"{self.tree.name}: not one CBOR data item: {exc}") from None
        if stream.tell() != len(data):
            raise rosgate.CodecError(f"{self.tree.name}: not one CBOR data item: "
                                     f"{len(data) - stream.tell()} bytes after it")
        return tree


@rosgate.hookimpl
def rosgate_codecs(register: Callable[[type[rosgate.Codec]], None]) -> None:
    register(CborCodec)
