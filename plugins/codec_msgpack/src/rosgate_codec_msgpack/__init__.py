"""rosgate codec ``msgpack``: a ROS message as a MessagePack map, for peers without ROS.

This is the wire format of the CVRA MessagePack bridge: a microcontroller with a small
MessagePack library reads and writes it without knowing anything about ROS or CDR.

Wire mapping (ROS field type -> MessagePack):

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

Decoding is strict, because the bytes come from the network: the top level must be a map; an
unknown field, a value of the wrong type, an integer out of its field's range, a fixed array of
the wrong length, a bounded sequence or string over its bound are each a
:class:`rosgate.CodecError` naming the field by its dotted path (``pose.position.w``,
``points[3].x``). Fields left out keep the message's defaults. An integer is accepted where a
float is expected (a microcontroller may send 0 for 0.0); a boolean is never taken for a number.

Framing ``none`` (one datagram per message, several topics on one port): the datagram is the
topic's name as a MessagePack str immediately followed by the map, as the CVRA bridge sends it.

All per-type work happens once: walking the rosidl definition (``SLOT_TYPES``) builds an
encoder and a decoder per field, cached per message class and shared by every topic of the
type; ``encode`` and ``decode`` only run them.
"""

from __future__ import annotations

import array
import importlib
import math
import struct
from dataclasses import dataclass
from functools import partial
from operator import attrgetter
from typing import Any, Callable, Mapping

import msgpack
import numpy
from rosidl_parser import definition as idl

import rosgate

Encoder = Callable[[Any], bytes]
Decoder = Callable[[Any], Any]

_packb = msgpack.packb
# float32 and float64 must keep their width on the wire, but a MessagePack packer writes every
# Python float the same way; so floats are packed here, format byte first.
_pack_float32: Encoder = partial(struct.Struct(">Bf").pack, 0xCA)
_pack_float64: Encoder = partial(struct.Struct(">Bd").pack, 0xCB)
# rclpy's own bound for float32 fields (a hair under FLT_MAX): what passes here passes rclpy
_FLOAT32_MAX = 3.402823466e38

_INTEGER_RANGES = {
    "int8": (-(2**7), 2**7 - 1), "uint8": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1), "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1), "uint64": (0, 2**64 - 1),
}
# rclpy keeps numeric sequences in array.array and fixed numeric arrays in numpy arrays, with
# these type codes (rosidl_generator_py's SPECIAL_NESTED_BASIC_TYPES; uint8 travels as bin)
_TYPECODES = {
    "float": "f", "double": "d", "int8": "b", "int16": "h", "uint16": "H",
    "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q",
}


@dataclass(frozen=True)
class _Converter:
    """How one field type travels: ROS value -> packed bytes, unpacked value -> ROS value."""

    encode: Encoder
    decode: Decoder


class _Invalid(Exception):
    """A received value that does not fit its field. The path is collected innermost first as
    the exception unwinds through the decoders, so the path costs nothing until something fails."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason
        self.path: list[str] = []

    def where(self) -> str:
        text = ""
        for part in reversed(self.path):
            text += part if part.startswith("[") or not text else "." + part
        return text


def _describe(value: Any) -> str:
    """A received value as the peer's MessagePack would call it, short enough for a log line."""
    if value is None:
        return "nil"
    if isinstance(value, (bool, int, float)):
        return repr(value)
    if isinstance(value, str):
        return f"str {value[:32]!r}" + ("..." if len(value) > 32 else "")
    if isinstance(value, bytes):
        return f"bin of {len(value)} bytes"
    if isinstance(value, list):
        return f"an array of {len(value)}"
    if isinstance(value, dict):
        return "a map"
    return type(value).__name__


def _type_name(t: idl.AbstractType) -> str:
    """A rosidl type spelled as ``get_fields_and_field_types()`` spells it."""
    if isinstance(t, idl.BasicType):
        return t.typename
    if isinstance(t, idl.NamespacedType):
        return f"{t.namespaces[0]}/{t.name}"
    if isinstance(t, idl.AbstractGenericString):
        base = "wstring" if isinstance(t, idl.AbstractWString) else "string"
        bound = getattr(t, "maximum_size", None)
        return base if bound is None else f"{base}<{bound}>"
    item = _type_name(t.value_type)
    if isinstance(t, idl.Array):
        return f"{item}[{t.size}]"
    if isinstance(t, idl.BoundedSequence):
        return f"sequence<{item}, {t.maximum_size}>"
    return f"sequence<{item}>"


def _array_header(length: int) -> bytes:
    if length < 16:
        return bytes((0x90 | length,))
    if length < 0x10000:
        return b"\xdc" + length.to_bytes(2, "big")
    return b"\xdd" + length.to_bytes(4, "big")


def _map_header(length: int) -> bytes:
    if length < 16:
        return bytes((0x80 | length,))
    if length < 0x10000:
        return b"\xde" + length.to_bytes(2, "big")
    return b"\xdf" + length.to_bytes(4, "big")


# -- scalars ----------------------------------------------------------------------------------

def _decode_bool(value: Any) -> bool:
    if type(value) is not bool:
        raise _Invalid(f"expected boolean, got {_describe(value)}")
    return value


def _int_decoder(typename: str) -> Decoder:
    low, high = _INTEGER_RANGES[typename]
    expected = f"expected {typename} (an integer in [{low}, {high}])"

    def decode(value: Any) -> int:
        # type(), not isinstance(): True is an int to Python, but not a number on the wire
        if type(value) is not int or not low <= value <= high:
            raise _Invalid(f"{expected}, got {_describe(value)}")
        return value
    return decode


def _decode_float64(value: Any) -> float:
    kind = type(value)
    if kind is float:
        return value
    if kind is int:
        return float(value)  # a MessagePack int has at most 64 bits: a double always holds it
    raise _Invalid(f"expected double (a number), got {_describe(value)}")


def _decode_float32(value: Any) -> float:
    kind = type(value)
    if kind is int:
        value = float(value)
    elif kind is not float:
        raise _Invalid(f"expected float (a number), got {_describe(value)}")
    if _FLOAT32_MAX < abs(value) < math.inf:
        raise _Invalid(f"expected float (within +-{_FLOAT32_MAX:g}), got {value!r}")
    return value


def _encode_octet(value: bytes) -> bytes:
    return _packb(value[0])  # rclpy holds a byte field as bytes of length 1


def _decode_octet(value: Any) -> bytes:
    if type(value) is not int or not 0 <= value <= 255:
        raise _Invalid(f"expected byte (an integer in [0, 255]), got {_describe(value)}")
    return bytes((value,))


def _scalar(typename: str) -> _Converter:
    if typename == "boolean":
        return _Converter(_packb, _decode_bool)
    if typename == "octet":
        return _Converter(_encode_octet, _decode_octet)
    if typename == "float":
        return _Converter(_pack_float32, _decode_float32)
    if typename == "double":
        return _Converter(_pack_float64, _decode_float64)
    if typename in _INTEGER_RANGES:
        return _Converter(_packb, _int_decoder(typename))
    # char, wchar, long double, short, long ...: IDL-only types that no .msg can declare
    raise rosgate.CodecError(f"the msgpack codec does not support the IDL type {typename!r}")


def _string(t: idl.AbstractGenericString) -> _Converter:
    bound = getattr(t, "maximum_size", None)
    expected = f"expected {_type_name(t)}"
    utf8 = not isinstance(t, idl.AbstractWString)

    def decode(value: Any) -> str:
        if type(value) is not str:
            raise _Invalid(f"{expected}, got {_describe(value)}")
        # the middleware bounds a string's UTF-8 bytes, which are never fewer than its
        # characters: encode only when the characters fit and the text is not plain ASCII
        if bound is not None and (len(value) > bound or (
                utf8 and not value.isascii() and len(value.encode()) > bound)):
            raise _Invalid(f"{expected}, got a str of {len(value.encode())} bytes")
        return value
    return _Converter(_packb, decode)


# -- arrays and sequences ---------------------------------------------------------------------

def _length_checker(t: idl.AbstractNestedType, wire: type, wire_name: str) -> Callable[[Any], None]:
    """Check a received collection's MessagePack type, and its length against the field's."""
    size = t.size if isinstance(t, idl.Array) else None
    bound = t.maximum_size if isinstance(t, idl.BoundedSequence) else None
    expected = f"expected {_type_name(t)} ({wire_name}"
    expected += f" of exactly {size})" if size is not None else (
        f" of at most {bound})" if bound is not None else ")")

    def check(value: Any) -> None:
        if type(value) is not wire or (size is not None and len(value) != size) or (
                bound is not None and len(value) > bound):
            raise _Invalid(f"{expected}, got {_describe(value)}")
    return check


def _bytes(t: idl.AbstractNestedType) -> _Converter:
    """uint8 and byte collections travel as bin: one copy, no per-element work."""
    check = _length_checker(t, bytes, "bin")

    if t.value_type.typename == "octet":  # rclpy: a list of bytes objects of length 1
        def encode(value: Any) -> bytes:
            return _packb(b"".join(value))

        def decode(value: Any) -> Any:
            check(value)
            return list(map(int.to_bytes, value))
    else:
        fixed = isinstance(t, idl.Array)

        def encode(value: Any) -> bytes:
            return _packb(memoryview(value))  # no copy of an image's pixels before packing

        def decode(value: Any) -> Any:
            check(value)
            # rclpy: a numpy uint8 array for uint8[N] (copied: frombuffer alone is read-only),
            # array.array('B') for uint8[]
            return numpy.frombuffer(value, numpy.uint8).copy() if fixed else array.array("B", value)
    return _Converter(encode, decode)


def _pack_float32s(values: Any) -> bytes:
    """Every element as float 32 (0xca + 4 bytes big-endian), laid out by numpy in one pass."""
    items = numpy.asarray(values, dtype=numpy.float32)
    packed = numpy.empty(len(items), dtype=[("format", "u1"), ("value", ">f4")])
    packed["format"] = 0xCA
    packed["value"] = items
    return _array_header(len(items)) + packed.tobytes()


def _encode_tolist(value: Any) -> bytes:
    return _packb(value.tolist())  # array.array and numpy both hand over Python numbers in C


def _beyond_float32(values: list[Any]) -> bool:
    magnitudes = numpy.abs(numpy.array(values, dtype=numpy.float64))
    return bool(((magnitudes > _FLOAT32_MAX) & (magnitudes < numpy.inf)).any())


def _numbers(t: idl.AbstractNestedType) -> _Converter:
    """Numeric collections, decoded by array.array in C (which also enforces integer ranges)."""
    typename = t.value_type.typename
    typecode = _TYPECODES[typename]
    check = _length_checker(t, list, "an array")
    allowed = {int, float} if typename in ("float", "double") else {int}  # bool is no number
    fixed = isinstance(t, idl.Array)
    float32 = typename == "float"
    # the scalar rules applied element by element: slower, but names the first bad element
    one_by_one = _items(t, _scalar(typename)).decode

    def decode(value: Any) -> Any:
        check(value)
        # array('f') would turn an out-of-range float32 into inf without a word
        if set(map(type, value)) <= allowed and not (float32 and _beyond_float32(value)):
            try:
                items = array.array(typecode, value)
                return numpy.array(items) if fixed else items
            except OverflowError:  # an integer outside the element type's range
                pass
        return one_by_one(value)  # the same rules, so this raises, naming the element

    return _Converter(_pack_float32s if float32 else _encode_tolist, decode)


def _items(t: idl.AbstractNestedType, item: _Converter) -> _Converter:
    """Collections of booleans, strings or messages: rclpy keeps them as lists."""
    check = _length_checker(t, list, "an array")
    encode_item, decode_item = item.encode, item.decode

    def encode(value: Any) -> bytes:
        return _array_header(len(value)) + b"".join(map(encode_item, value))

    def decode(value: Any) -> list[Any]:
        check(value)
        items: list[Any] = []
        try:
            for element in value:
                items.append(decode_item(element))
        except _Invalid as exc:
            exc.path.append(f"[{len(items)}]")
            raise
        return items
    return _Converter(encode, decode)


def _collection(t: idl.AbstractNestedType) -> _Converter:
    item = t.value_type
    if isinstance(item, idl.BasicType) and item.typename in ("uint8", "octet"):
        return _bytes(t)
    if isinstance(item, idl.BasicType) and item.typename in _TYPECODES:
        return _numbers(t)
    return _items(t, _converter(item))


def _converter(t: idl.AbstractType) -> _Converter:
    if isinstance(t, idl.BasicType):
        return _scalar(t.typename)
    if isinstance(t, idl.AbstractGenericString):
        return _string(t)
    if isinstance(t, idl.NamespacedType):
        nested = _message(getattr(importlib.import_module(".".join(t.namespaces)), t.name))
        return _Converter(nested.encode, nested.decode)
    if isinstance(t, idl.AbstractNestedType):
        return _collection(t)
    raise rosgate.CodecError(f"the msgpack codec does not support {type(t).__name__}")


# -- messages ---------------------------------------------------------------------------------

class _Message:
    """Encoder and decoder of one message class: its fields' converters, by name."""

    def __init__(self, msg_type: type):
        self.msg_type = msg_type
        self.name = f"{msg_type.__module__.split('.')[0]}/{msg_type.__name__}"
        names = list(msg_type.get_fields_and_field_types())
        converters = [_converter(slot_type) for slot_type in msg_type.SLOT_TYPES]
        self.header = _map_header(len(names))
        self.encoders = [(_packb(name), attrgetter(name), convert.encode)
                         for name, convert in zip(names, converters)]
        self.decoders = {name: convert.decode for name, convert in zip(names, converters)}

    def encode(self, message: Any) -> bytes:
        return self.header + b"".join(
            [key + encode(get(message)) for key, get, encode in self.encoders])

    def decode(self, value: Any) -> Any:
        if type(value) is not dict:
            raise _Invalid(f"expected a map of {self.name} fields, got {_describe(value)}")
        fields = {}
        for key, item in value.items():
            decode = self.decoders.get(key)
            if decode is None:
                exc = _Invalid(f"unknown field of {self.name} (it has: {', '.join(self.decoders)})")
                exc.path.append(str(key))
                raise exc
            try:
                fields[key] = decode(item)
            except _Invalid as exc:
                exc.path.append(key)
                raise
        return self.msg_type(**fields)  # fields left out keep the constructor's defaults


# One converter tree per message class, shared by every codec instance; a Header is built once
# however many message types contain one.
_MESSAGES: dict[type, _Message] = {}


def _message(msg_type: type) -> _Message:
    message = _MESSAGES.get(msg_type)
    if message is None:
        message = _MESSAGES[msg_type] = _Message(msg_type)
    return message


# -- the codec --------------------------------------------------------------------------------

def _unpack_limits(size: int) -> dict[str, int]:
    # nothing in the input is longer than the input: a forged length cannot make us allocate;
    # ext types (timestamps included) mean nothing in a ROS message
    return {"max_bin_len": size, "max_str_len": size, "max_array_len": size,
            "max_map_len": size, "max_ext_len": 0}


# What msgpack raises for bytes it cannot read: ExtraData, FormatError, StackError and
# UnicodeDecodeError are ValueErrors, OutOfData and BufferFull UnpackExceptions, and TypeError
# comes for something that is not bytes at all.
_UNREADABLE = (ValueError, TypeError, msgpack.UnpackException)
# What a field holding the wrong kind of value raises while packing; only a message filled with
# rclpy's field checks off (the default) can hold one.
_UNENCODABLE = (TypeError, ValueError, OverflowError, AttributeError, BufferError, struct.error)


class MsgpackCodec(rosgate.Codec):
    """ROS messages as MessagePack maps; the module documentation has the mapping."""

    name = "msgpack"
    raw = False
    names_bare_frames = True

    def __init__(self, msg_type: type, options: Mapping[str, Any]):
        super().__init__(msg_type, options)
        for key in self.options:
            raise rosgate.OptionError(key, f"the msgpack codec has no option {key!r}",
                                      fix="remove it from plugins: msgpack:")
        self._message = _message(msg_type)

    def encode(self, message: Any) -> bytes:
        if type(message) is not self.msg_type:
            raise rosgate.CodecError(
                f"expected a {self._message.name} message, got {type(message).__name__}")
        try:
            return self._message.encode(message)
        except _UNENCODABLE as exc:
            raise rosgate.CodecError(f"cannot encode this {self._message.name}: {exc}") from None

    def decode(self, data: bytes) -> Any:
        try:
            tree = msgpack.unpackb(data, raw=False, strict_map_key=True,
                                   **_unpack_limits(len(data)))
        except _UNREADABLE as exc:
            reason = str(exc) or type(exc).__name__
            raise rosgate.CodecError(
                f"{self._message.name}: not one MessagePack object: {reason}") from None
        try:
            return self._message.decode(tree)
        except _Invalid as exc:
            where = f"{exc.where()}: " if exc.path else ""
            raise rosgate.CodecError(f"{self._message.name}: {where}{exc.reason}") from None

    def encode_bare(self, name: str, message: Any) -> bytes:
        return _packb(name) + self.encode(message)

    @classmethod
    def split_bare(cls, datagram: bytes) -> tuple[str | None, bytes]:
        unpacker = msgpack.Unpacker(raw=False, strict_map_key=True,
                                    max_buffer_size=max(len(datagram), 1),
                                    **_unpack_limits(len(datagram)))
        try:
            unpacker.feed(datagram)
            name = unpacker.unpack()
        except _UNREADABLE as exc:
            reason = str(exc) or type(exc).__name__
            raise rosgate.CodecError(
                f"bare datagram: no MessagePack object at its start: {reason}") from None
        if type(name) is not str:
            raise rosgate.CodecError(
                f"bare datagram: expected the topic's name (a str) first, got {_describe(name)}")
        return name, datagram[unpacker.tell():]

    def decode_bare(self, rest: bytes) -> Any:
        return self.decode(rest)


@rosgate.hookimpl
def rosgate_codecs(register: Callable[[type[rosgate.Codec]], None]) -> None:
    register(MsgpackCodec)
