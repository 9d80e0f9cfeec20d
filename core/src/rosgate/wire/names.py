"""A name in front of a bare datagram: the CVRA profile's ``framing: none`` and its service
requests write the topic's (or service's) name as a MessagePack str, followed by the payload.

Only the str forms of MessagePack are written and read (fixstr, str 8, str 16, str 32), so the
core needs no MessagePack library for them; what follows the name is the codec's business.
"""

from __future__ import annotations

import struct

_STR8, _STR16, _STR32 = 0xD9, 0xDA, 0xDB
_LENGTH = {_STR8: struct.Struct(">B"), _STR16: struct.Struct(">H"), _STR32: struct.Struct(">I")}


class NameMissing(ValueError):
    """A bare datagram that does not start with a name."""


def pack_name(name: str) -> bytes:
    data = name.encode()
    size = len(data)
    if size < 32:
        return bytes((0xA0 | size,)) + data
    for code in (_STR8, _STR16, _STR32):
        length = _LENGTH[code]
        if size < 1 << (8 * length.size):
            return bytes((code,)) + length.pack(size) + data
    raise ValueError(f"a name of {size} bytes is too long")


def split_name(datagram: bytes | memoryview) -> tuple[str, bytes]:
    """(name, the bytes after it); :class:`NameMissing` when the datagram does not start with
    a MessagePack str."""
    if not datagram:
        raise NameMissing("empty datagram")
    head = datagram[0]
    if head & 0xE0 == 0xA0:
        start, size = 1, head & 0x1F
    elif head in _LENGTH:
        length = _LENGTH[head]
        if len(datagram) < 1 + length.size:
            raise NameMissing("truncated name length")
        start, (size,) = 1 + length.size, length.unpack_from(datagram, 1)
    else:
        raise NameMissing(f"expected the name (a MessagePack str) first, got a byte 0x{head:02x}")
    end = start + size
    if end > len(datagram):
        raise NameMissing(f"a name of {size} bytes in a datagram of {len(datagram)}")
    try:
        name = bytes(datagram[start:end]).decode()
    except UnicodeDecodeError:
        raise NameMissing("the name is not UTF-8") from None
    return name, bytes(datagram[end:])
