"""rosgate codec ``cbor``: a ROS message as a CBOR map (RFC 8949), for peers without ROS.

CBOR is MessagePack's standardised cousin (an IETF RFC, with libraries for every language and
for microcontrollers: TinyCBOR, QCBOR, nanocbor). The mapping is the one the ``msgpack`` codec
uses, shared through :mod:`rosgate_message_tree`; in CBOR terms:

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

Writing uses definite lengths only, and no tags. Reading is strict, because the bytes come from
the network: anything but exactly one CBOR data item is refused (trailing bytes too), as are
map keys that are not text or byte strings, duplicate keys, nesting deeper than 64, every tag
(this codec writes none: dates, bignums, and above all cbor2's shared values, tags 28 and 29,
with which 24 kB became 36 million floats), more arrays and maps than one per 8 bytes of input
(:func:`rosgate_message_tree.container_budget`; checked by a walk over the items before they
are built, for inputs over 1 kB), and any tree that does not fit the message (an unknown field,
a value of the wrong type or range, a fixed array of the wrong length, a bounded sequence or
string over its bound) — each a :class:`rosgate.CodecError` naming the field by its dotted path
(``pose.position.w``). Fields left out keep the message's defaults; an integer is accepted where
a float is expected (half-precision floats too); a boolean is never a number.

Options: none. Framing ``none`` carries the map alone (one topic per port).
"""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any

import cbor2
from rosgate_message_tree import BUDGET_FROM, OverBudget, TreeCodec, WireFormat, container_budget

import rosgate


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


def _refuse_tag(*args: Any) -> Any:
    raise cbor2.CBORDecodeError("a tag (this codec writes none)")


def _refuse_unknown_tag(tag: Any, immutable: bool) -> Any:
    raise cbor2.CBORDecodeError(f"tag {tag.tag} (this codec writes none)")


# cbor2 decodes these tags itself, before any tag hook sees them: each is refused here (a test
# checks that every tag up to 70,000 is, so a cbor2 that learns a new one is noticed)
_KNOWN_TAGS = {tag: _refuse_tag for tag in (*range(300), 1004, 1040, 43000, 55799, 55800, 55801)}


def check_items(data: bytes) -> None:
    """Walk the CBOR items of ``data`` without building them: :class:`OverBudget` for more
    arrays and maps than its size allows, ValueError for a tag, an indefinite length, or a
    length longer than what is left. Linear in the input; strings and runs of floats are
    stepped over whole."""
    budget = container_budget(len(data))
    end, pos, pending = len(data), 0, 1
    while pending:
        if pos >= end:
            raise ValueError("truncated")
        head = data[pos]
        major, info = head >> 5, head & 0x1F
        pos += 1
        if info < 24:
            argument = info
        elif info < 28:
            width = 1 << (info - 24)
            argument = int.from_bytes(data[pos:pos + width], "big")
            pos += width
        else:
            raise ValueError("an indefinite length or a reserved head")
        pending -= 1
        if major in (2, 3):  # a byte or text string
            pos += argument
        elif major in (4, 5):  # an array or a map
            budget -= 1
            if budget < 0:
                raise OverBudget(f"more than {container_budget(end)} arrays and maps in "
                                 f"{end} bytes")
            items = argument if major == 4 else 2 * argument
            if items > end - pos:
                raise ValueError("more items than bytes left")
            pending += items
            if major == 4 and items and data[pos] in _FLOAT_STRIDES:
                stride = _FLOAT_STRIDES[data[pos]]
                if data[pos:pos + stride * items:stride] == bytes((data[pos],)) * items:
                    pos += stride * items  # a run of floats of one width: stepped over at once
                    pending -= items
        elif major == 6:
            raise ValueError("a tag (this codec writes none)")
        # 0, 1: integers; 7: simple values and floats, their bytes already stepped over
    if pos > end:
        raise ValueError("truncated")


_FLOAT_STRIDES = {0xF9: 3, 0xFA: 5, 0xFB: 9}


class CborCodec(TreeCodec):
    """ROS messages as CBOR maps; the module documentation has the mapping."""

    name = "cbor"
    wire = CBOR

    def parse(self, data: bytes) -> Any:
        try:
            if len(data) > BUDGET_FROM:
                check_items(data)
        except ValueError as exc:  # OverBudget too
            raise rosgate.CodecError(f"{self.tree.name}: not one CBOR data item: {exc}") from None
        stream = io.BytesIO(data)
        try:
            tree = cbor2.CBORDecoder(stream, max_depth=MAX_DEPTH, allow_duplicate_keys=False,
                                     strict_hashable_types=True, tag_hook=_refuse_unknown_tag,
                                     semantic_decoders=_KNOWN_TAGS).decode()
        except cbor2.CBORDecodeError as exc:  # every unreadable input, tags' contents included
            raise rosgate.CodecError(f"{self.tree.name}: not one CBOR data item: {exc}") from None
        if stream.tell() != len(data):
            raise rosgate.CodecError(f"{self.tree.name}: not one CBOR data item: "
                                     f"{len(data) - stream.tell()} bytes after it")
        return tree


@rosgate.hookimpl
def rosgate_codecs(register: Callable[[type[rosgate.Codec]], None]) -> None:
    register(CborCodec)
