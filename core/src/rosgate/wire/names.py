"""A name in front of a bare datagram: the microcontroller (CVRA) profile's ``framing: none``
and its service requests carry the topic's (or service's) name, then its arguments, laid out
``array`` (``[name, args]``: one MessagePack array of two, as CVRA's firmware and ``cvra_rpc``
write) or ``pair`` (the name, then the arguments, as the CVRA README says), told apart on receipt
by the first byte. Only two-element array headers and MessagePack's str forms are read and
written here, so the core needs no MessagePack library; the arguments are the codec's business.
"""

from __future__ import annotations

import struct
from enum import StrEnum


class Layout(StrEnum):
    """How a bare datagram (or a serial-datagram request) lays out its name and arguments."""

    #: ``[name, args]``: one MessagePack array of two elements (CVRA's firmware and cvra_rpc)
    ARRAY = "array"
    #: ``name`` then ``args``: two MessagePack objects one after the other (the CVRA README)
    PAIR = "pair"


LAYOUT_DEFAULT = Layout.ARRAY

# str 8, str 16, str 32: the byte that says which, then the length
_LENGTH = {0xD9: struct.Struct(">B"), 0xDA: struct.Struct(">H"), 0xDB: struct.Struct(">I")}
# an array of exactly two elements: fixarray, and the array 16 / array 32 forms some packers use
_PAIR_ARRAYS = (b"\x92", b"\xdc\x00\x02", b"\xdd\x00\x00\x00\x02")


class NameMissing(ValueError):
    """A bare datagram in neither layout."""


def pack_name(name: str, layout: Layout = Layout.PAIR) -> bytes:
    """What goes in front of the arguments: the name as a MessagePack str, behind the header of
    an array of two for the array layout."""
    data = name.encode()
    size = len(data)
    head = b"\x92" if layout is Layout.ARRAY else b""
    if size < 32:
        return head + bytes((0xA0 | size,)) + data
    for code, length in _LENGTH.items():
        if size < 1 << (8 * length.size):
            return head + bytes((code,)) + length.pack(size) + data
    raise ValueError(f"a name of {size} bytes is too long")


def split_name(datagram: bytes | memoryview) -> tuple[str, bytes]:
    """(name, the bytes of the arguments), whichever layout the datagram has;
    :class:`NameMissing` when it has neither."""
    if not datagram:
        raise NameMissing("empty datagram")
    at = 0
    head = datagram[0]
    if head & 0xF0 == 0x90 or head in (0xDC, 0xDD):
        at = next((len(a) for a in _PAIR_ARRAYS if bytes(datagram[:len(a)]) == a), 0)
        if not at:
            elements = (f"{head & 0x0F} elements" if head & 0xF0 == 0x90
                        else "array 16 or 32 of another length, or truncated")
            raise NameMissing(f"neither layout: an array that is not [name, args] (first byte "
                              f"0x{head:02x}: {elements})")
        if at >= len(datagram):
            raise NameMissing("an array [name, args] that ends before its name")
        head = datagram[at]
    if head & 0xE0 == 0xA0:
        start, size = at + 1, head & 0x1F
    elif head in _LENGTH:
        length = _LENGTH[head]
        if len(datagram) < at + 1 + length.size:
            raise NameMissing("truncated name length")
        start, (size,) = at + 1 + length.size, length.unpack_from(datagram, at + 1)
    elif at:
        raise NameMissing(f"an array [name, args] whose name is not a MessagePack str "
                          f"(byte 0x{head:02x})")
    else:
        raise NameMissing(f"neither layout: expected [name, args] (a MessagePack array of two, "
                          f"0x92) or a name (a MessagePack str) first, got a byte 0x{head:02x}")
    end = start + size
    if end > len(datagram):
        raise NameMissing(f"a name of {size} bytes in a datagram of {len(datagram)}")
    try:
        name = bytes(datagram[start:end]).decode()
    except UnicodeDecodeError:
        raise NameMissing("the name is not UTF-8") from None
    return name, bytes(datagram[end:])


def call_shaped(datagram: bytes | memoryview) -> bool:
    """Whether a datagram looks like a call on a serial line (``[name, args, id]``: an array of
    three) or its answer (``[id, value]``: an array of two whose first item is an unsigned
    integer), never like a message: those belong to the line's calls (docs/microcontrollers.md)."""
    if len(datagram) < 2:
        return False
    return datagram[0] == 0x93 or datagram[0] == 0x92 and (datagram[1] < 0x80
                                                           or 0xCC <= datagram[1] <= 0xCF)
