"""ROS messages as trees of maps, arrays and scalars: the mapping shared by the tree codecs
(``msgpack``, ``cbor``, and any plugin that writes a self-describing format of the same kind).

The mapping (ROS field type -> tree node):

=================================  ===========================================================
ROS                                tree node
=================================  ===========================================================
message (nested ones too)          map: field name as in the .msg -> value, in .msg order
bool                               boolean
int8 ... int64, uint8 ... uint64   integer (the format's smallest encoding)
byte                               integer in [0, 255]
float32                            float of 32 bits (the format's single-precision tag)
float64                            float of 64 bits
string, wstring                    text (UTF-8)
uint8[], uint8[N], byte[], byte[N] byte string (the bytes as they are)
any other T[], T[N], T[<=N]        array of T (float32 elements as 32-bit floats)
builtin_interfaces/Time, Duration  nothing special: {"sec": ..., "nanosec": ...}
=================================  ===========================================================

A format plugs in with a :class:`WireFormat`: how it writes the few things the mapping writes
itself (headers of maps, arrays and byte strings, the two float widths) and its packer for
plain values. Writing goes straight to bytes, field by field, without building a tree first;
reading takes the tree the format's own parser returns (dicts, lists, bytes, str, int, float,
bool) and checks it strictly, because it comes from the network: an unknown field, a value of
the wrong type, an integer out of its field's range, a fixed array of the wrong length, a
bounded sequence or string over its bound are each a :class:`TreeError` naming the field by
its dotted path (``pose.position.w``, ``points[3].x``). Fields left out keep the message's
defaults. An integer is accepted where a float is expected (a microcontroller may send 0 for
0.0); a boolean is never taken for a number.

All per-type work happens once: walking the rosidl definition (``SLOT_TYPES``) builds an
encoder and a decoder per field, cached per message class and format; encoding and decoding
only run them. :class:`TreeCodec` is the codec base class that puts this behind
:class:`rosgate.Codec`: a format's codec adds its name, its :class:`WireFormat` and its parser.

A format's parser has a budget (:class:`ContainerBudget`): it may build at most
:func:`container_budget` arrays and maps for an input of a given size (one per 8 bytes, plus
64). An empty map is one byte on the wire and some 64 in Python, so without it 4 MB of empty
maps became 277 MB; with it, memory stays within a few times the input's size. Formats with
references or tags that expand (CBOR's shared values) refuse them outright.

A format that has a library turning plain Python values into text and back (JSON, YAML, TOML)
uses the mapping through two functions instead, with the same strict checks:

* :func:`to_tree` ``(message)``: the message as plain Python — ``dict`` (field name -> value, in
  .msg order), ``list``, ``str``, ``int``, ``float``, ``bool`` and ``bytes`` (for ``uint8[]`` and
  ``byte[]`` fields) — following the table above.
* :func:`from_tree` ``(msg_type, tree)``: the message a tree of the same kind describes, or
  :class:`rosgate.CodecError` naming the field by its dotted path.

Both take ``base64=True`` for a format without byte strings: ``uint8[]`` and ``byte[]`` fields are
then base64 text (RFC 4648, standard alphabet, padded), and ``from_tree`` refuses text that is
not. ``tests/thirdparty/codec_json/`` is a JSON codec written with them.

This library needs the ROS Python packages (``rosidl_parser``, numpy); a bridge loads it only
through a tree codec that depends on it.
"""

from __future__ import annotations

import array
import base64 as b64
import dataclasses
import importlib
import math
import struct
from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, partial
from operator import attrgetter
from typing import Any, ClassVar

from rosidl_parser import definition as idl

from rosgate import Codec, CodecError

Encoder = Callable[[Any], bytes]
Decoder = Callable[[Any], Any]
ToTree = Callable[[Any], Any]

# the largest finite float32 (FLT_MAX, 0x7f7fffff), which rclpy's own deserializer hands over;
# rclpy's field check (ROS_PYTHON_CHECK_FIELDS=1) rounds it to 3.402823466e38 and would refuse it
FLOAT32_MAX: float = struct.unpack(">f", bytes.fromhex("7f7fffff"))[0]

_INTEGER_RANGES = {
    "int8": (-(2**7), 2**7 - 1), "uint8": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1), "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1), "uint64": (0, 2**64 - 1),
}
# rclpy keeps numeric sequences in array.array and fixed numeric arrays in numpy arrays, with
# these type codes (rosidl_generator_py's SPECIAL_NESTED_BASIC_TYPES; uint8 travels as bytes)
_TYPECODES = {
    "float": "f", "double": "d", "int8": "b", "int16": "h", "uint16": "H",
    "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q",
}


@dataclass(frozen=True)
class WireFormat:
    """What a tree format tells the mapping about itself."""

    #: the format's name, for messages (``MessagePack``)
    name: str
    #: packs a bool, an int, a str, or a list of ints or of float64s, as the format does
    pack: Encoder
    #: one-byte tags before a big-endian IEEE float of 32 and of 64 bits (MessagePack 0xca and
    #: 0xcb, CBOR 0xfa and 0xfb): a packer writes every Python float alike, so the mapping
    #: writes floats itself to keep float32 fields 32 bits wide
    float32_tag: int
    float64_tag: int
    #: headers of an array, a map, a byte string of n elements (bytes)
    array_header: Callable[[int], bytes]
    map_header: Callable[[int], bytes]
    bytes_header: Callable[[int], bytes]
    #: how the format's users call a byte string, a text string and nil, for error messages
    bytes_word: str = "bin"
    str_word: str = "str"
    nil_word: str = "nil"
    #: True for a format without byte strings: ``uint8[]`` and ``byte[]`` fields are base64 text
    base64: bool = False
    #: True: float64 fields are written as 32-bit floats too (a microcontroller's single
    #: precision); reading takes either width for either field
    float64_as_float32: bool = False


@dataclass(frozen=True)
class _Converter:
    """How one field type travels: ROS value -> packed bytes, parsed value -> ROS value, and
    ROS value -> plain Python value (:func:`to_tree`)."""

    encode: Encoder
    decode: Decoder
    tree: ToTree


class TreeError(Exception):
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


def describe(value: Any, wire: WireFormat) -> str:
    """A received value as the peer's format would call it, short enough for a log line."""
    if value is None:
        return wire.nil_word
    if isinstance(value, (bool, int, float)):
        return repr(value)
    if isinstance(value, str):
        return f"{wire.str_word} {value[:32]!r}" + ("..." if len(value) > 32 else "")
    if isinstance(value, bytes):
        return f"{wire.bytes_word} of {len(value)} bytes"
    if isinstance(value, list):
        return f"an array of {len(value)}"
    if isinstance(value, dict):
        return "a map"
    return type(value).__name__


def type_name(t: idl.AbstractType) -> str:
    """A rosidl type spelled as ``get_fields_and_field_types()`` spells it."""
    if isinstance(t, idl.BasicType):
        return t.typename
    if isinstance(t, idl.NamespacedType):
        return f"{t.namespaces[0]}/{t.name}"
    if isinstance(t, idl.AbstractGenericString):
        base = "wstring" if isinstance(t, idl.AbstractWString) else "string"
        bound = getattr(t, "maximum_size", None)
        return base if bound is None else f"{base}<{bound}>"
    item = type_name(t.value_type)
    if isinstance(t, idl.Array):
        return f"{item}[{t.size}]"
    if isinstance(t, idl.BoundedSequence):
        return f"sequence<{item}, {t.maximum_size}>"
    return f"sequence<{item}>"


class _Builder:
    """Builds the converters of one format."""

    def __init__(self, wire: WireFormat):
        self.wire = wire
        self.pack = wire.pack
        self.float32 = struct.Struct(">Bf")
        self.float64 = struct.Struct(">Bd")

    def invalid(self, expected: str, value: Any) -> TreeError:
        return TreeError(f"{expected}, got {describe(value, self.wire)}")

    # -- scalars ------------------------------------------------------------------------------

    def scalar(self, typename: str) -> _Converter:
        invalid = self.invalid
        if typename == "boolean":
            def decode_bool(value: Any) -> bool:
                if type(value) is not bool:
                    raise invalid("expected boolean", value)
                return value
            return _Converter(self.pack, decode_bool, _of_kind(bool))
        if typename == "octet":
            pack = self.pack

            def encode_octet(value: bytes) -> bytes:
                return pack(value[0])  # rclpy holds a byte field as bytes of length 1

            def decode_octet(value: Any) -> bytes:
                if type(value) is not int or not 0 <= value <= 255:
                    raise invalid("expected byte (an integer in [0, 255])", value)
                return bytes((value,))
            return _Converter(encode_octet, decode_octet, _first_byte)
        if typename in ("float", "double"):
            return self.floating(typename)
        if typename in _INTEGER_RANGES:
            low, high = _INTEGER_RANGES[typename]
            expected = f"expected {typename} (an integer in [{low}, {high}])"

            def decode_int(value: Any) -> int:
                # type(), not isinstance(): True is an int to Python, but not a number on the wire
                if type(value) is not int or not low <= value <= high:
                    raise invalid(expected, value)
                return value
            return _Converter(self.pack, decode_int, _of_kind(int))
        # char, wchar, long double, short, long ...: IDL-only types that no .msg can declare
        raise CodecError(f"the {self.wire.name} mapping does not support the IDL type {typename!r}")

    def floating(self, typename: str) -> _Converter:
        invalid = self.invalid
        single = typename == "float"
        expected = f"expected {typename} (a number)"
        encode: Encoder = partial(self.float32.pack, self.wire.float32_tag) \
            if single or self.wire.float64_as_float32 else \
            partial(self.float64.pack, self.wire.float64_tag)

        def decode(value: Any) -> float:
            kind = type(value)
            if kind is float:
                number = value
            elif kind is int:
                try:
                    number = float(value)  # a format's bignum may be past any double
                except OverflowError:
                    raise invalid(expected, value) from None
            else:
                raise invalid(expected, value)
            if single and FLOAT32_MAX < abs(number) < math.inf:
                raise TreeError(f"expected float (within +-{FLOAT32_MAX:g}), got {value!r}")
            return number
        return _Converter(encode, decode, _of_kind(float, int))

    def string(self, t: idl.AbstractGenericString) -> _Converter:
        bound = getattr(t, "maximum_size", None)
        expected = f"expected {type_name(t)}"
        utf8 = not isinstance(t, idl.AbstractWString)
        invalid = self.invalid

        def decode(value: Any) -> str:
            if type(value) is not str:
                raise invalid(expected, value)
            if not value.isascii():
                try:
                    value.encode("utf-8" if utf8 else "utf-16-le")
                except UnicodeEncodeError:  # JSON's "\ud800": a str no middleware can carry
                    raise TreeError(f"{expected}, got text with an unpaired surrogate") from None
            # a bound counts characters, as rclpy's own field check does (and what rclpy
            # deserializes from CDR may be up to the bound in characters, more in bytes)
            if bound is not None and len(value) > bound:
                raise TreeError(f"{expected}, got a {self.wire.str_word} of {len(value)} "
                                "characters")
            return value
        return _Converter(self.pack, decode, _of_kind(str))

    # -- arrays and sequences -----------------------------------------------------------------

    def length_checker(self, t: idl.AbstractNestedType, wire_type: Any,
                       wire_name: str) -> Callable[[Any], None]:
        """Check a received collection's type, and its length against the field's."""
        size = t.size if isinstance(t, idl.Array) else None
        bound = t.maximum_size if isinstance(t, idl.BoundedSequence) else None
        expected = f"expected {type_name(t)} ({wire_name}"
        expected += f" of exactly {size})" if size is not None else (
            f" of at most {bound})" if bound is not None else ")")
        invalid = self.invalid

        def check(value: Any) -> None:
            if type(value) is not wire_type:
                raise invalid(expected, value)
            length = len(value)  # a sized type: bytes, str, list, array
            if size is not None and length != size or bound is not None and length > bound:
                raise invalid(expected, value)
        return check

    def bytes(self, t: idl.AbstractNestedType) -> _Converter:
        """uint8 and byte collections travel as a byte string: one copy, no per-element work
        (as base64 text in a format without byte strings)."""
        check = self.length_checker(t, bytes, self.wire.bytes_word)
        header, pack, invalid = self.wire.bytes_header, self.pack, self.invalid
        raw: Callable[[Any], Any]

        if t.value_type.typename == "octet":  # rclpy: a list of bytes objects of length 1
            raw = b"".join

            def build(data: bytes) -> Any:
                return list(map(int.to_bytes, data))
        else:
            import numpy  # here, not at the top: loading a tree codec's plugin needs no numpy

            fixed = isinstance(t, idl.Array)
            raw = memoryview  # no copy of an image's pixels before writing them

            def build(data: bytes) -> Any:
                # rclpy: a numpy uint8 array for uint8[N] (copied: frombuffer alone is
                # read-only), array.array('B') for uint8[]
                return (numpy.frombuffer(data, numpy.uint8).copy() if fixed
                        else array.array("B", data))

        if not self.wire.base64:
            def encode(value: Any) -> bytes:
                data = raw(value)
                return header(len(data)) + data

            def decode(value: Any) -> Any:
                check(value)
                return build(value)
            return _Converter(encode, decode, lambda value: bytes(raw(value)))

        expected = f"expected {type_name(t)} (base64 text)"

        def text(value: Any) -> str:
            return b64.b64encode(raw(value)).decode("ascii")

        def decode_text(value: Any) -> Any:
            if type(value) is not str:
                raise invalid(expected, value)
            try:
                data = b64.b64decode(value, validate=True)
            except ValueError:  # binascii.Error, or characters that are not ASCII
                raise invalid(expected, value) from None
            check(data)
            return build(data)
        return _Converter(lambda value: pack(text(value)), decode_text, text)

    def numbers(self, t: idl.AbstractNestedType) -> _Converter:
        """Numeric collections, decoded by array.array in C (which also enforces integer ranges)."""
        import numpy  # here, not at the top: loading a tree codec's plugin needs no numpy

        typename = t.value_type.typename
        typecode = _TYPECODES[typename]
        check = self.length_checker(t, list, "an array")
        allowed = {int, float} if typename in ("float", "double") else {int}  # bool is no number
        fixed = isinstance(t, idl.Array)
        single = typename == "float"
        # the scalar rules applied element by element: slower, but names the first bad element
        one_by_one = self.items(t, self.scalar(typename)).decode
        pack, array_header, tag = self.pack, self.wire.array_header, self.wire.float32_tag

        def encode_float32s(values: Any) -> bytes:
            """Every element as a tagged 32-bit float, laid out by numpy in one pass."""
            items = numpy.asarray(values, dtype=numpy.float32)
            packed = numpy.empty(len(items), dtype=[("tag", "u1"), ("value", ">f4")])
            packed["tag"] = tag
            packed["value"] = items
            return array_header(len(items)) + packed.tobytes()

        def encode_tolist(value: Any) -> bytes:
            return pack(value.tolist())  # array.array and numpy hand over Python numbers in C

        def beyond_float32(values: list[Any]) -> bool:
            magnitudes = numpy.abs(numpy.array(values, dtype=numpy.float64))
            return bool(((magnitudes > FLOAT32_MAX) & (magnitudes < numpy.inf)).any())

        def decode(value: Any) -> Any:
            check(value)
            if set(map(type, value)) <= allowed:
                try:
                    # array('f') would turn an out-of-range float32 into inf without a word
                    if not (single and beyond_float32(value)):
                        items = array.array(typecode, value)
                        return numpy.array(items) if fixed else items
                except OverflowError:  # an integer outside the element type's range
                    pass
            return one_by_one(value)  # the same rules, so this raises, naming the element

        as_float32 = single or typename == "double" and self.wire.float64_as_float32
        return _Converter(encode_float32s if as_float32 else encode_tolist, decode, _tolist)

    def items(self, t: idl.AbstractNestedType, item: _Converter) -> _Converter:
        """Collections of booleans, strings or messages: rclpy keeps them as lists."""
        check = self.length_checker(t, list, "an array")
        encode_item, decode_item, item_tree = item.encode, item.decode, item.tree
        array_header = self.wire.array_header

        def encode(value: Any) -> bytes:
            return array_header(len(value)) + b"".join(map(encode_item, value))

        def decode(value: Any) -> list[Any]:
            check(value)
            items: list[Any] = []
            try:
                for element in value:
                    items.append(decode_item(element))
            except TreeError as exc:
                exc.path.append(f"[{len(items)}]")
                raise
            return items

        def tree(value: Any) -> list[Any]:
            return list(map(item_tree, value))
        return _Converter(encode, decode, tree)

    def collection(self, t: idl.AbstractNestedType) -> _Converter:
        item = t.value_type
        if isinstance(item, idl.BasicType) and item.typename in ("uint8", "octet"):
            return self.bytes(t)
        if isinstance(item, idl.BasicType) and item.typename in _TYPECODES:
            return self.numbers(t)
        return self.items(t, self.converter(item))

    def converter(self, t: idl.AbstractType) -> _Converter:
        if isinstance(t, idl.BasicType):
            return self.scalar(t.typename)
        if isinstance(t, idl.AbstractGenericString):
            return self.string(t)
        if isinstance(t, idl.NamespacedType):
            nested = message_tree(getattr(importlib.import_module(".".join(t.namespaces)), t.name),
                                  self.wire)
            return _Converter(nested.encode, nested.decode, nested.to_tree)
        if isinstance(t, idl.AbstractNestedType):
            return self.collection(t)
        raise CodecError(f"the {self.wire.name} mapping does not support {type(t).__name__}")


def _of_kind(*kinds: type) -> Callable[[Any], Any]:
    """A scalar's side of a plain tree: the value itself, when it is of one of ``kinds`` (what
    rclpy's field checks allow); a TypeError (a :class:`rosgate.CodecError` to the caller) for a
    value of another kind, which a message with the checks off can hold."""
    def tree(value: Any) -> Any:
        if type(value) not in kinds:
            raise TypeError(f"a field holds a {type(value).__name__} where a "
                            f"{kinds[0].__name__} belongs")
        return value
    return tree


def _first_byte(value: bytes) -> int:
    return value[0]  # rclpy holds a byte field as bytes of length 1


def _tolist(value: Any) -> list[Any]:
    return value.tolist()  # array.array and numpy hand over Python numbers in C


# -- messages ---------------------------------------------------------------------------------

class MessageTree:
    """Encoder and decoder of one message class in one format: its fields' converters."""

    def __init__(self, msg_type: Any, wire: WireFormat):
        self.msg_type = msg_type
        self.name = f"{msg_type.__module__.split('.')[0]}/{msg_type.__name__}"
        self.wire = wire
        build = _Builder(wire)
        self.names = list(msg_type.get_fields_and_field_types())
        self.converters = [build.converter(slot_type) for slot_type in msg_type.SLOT_TYPES]
        self.decoders = {name: convert.decode
                         for name, convert in zip(self.names, self.converters, strict=True)}
        self.trees = [(name, attrgetter(name), convert.tree)
                      for name, convert in zip(self.names, self.converters, strict=True)]

    @cached_property
    def writers(self) -> tuple[bytes, list[tuple[bytes, Callable[[Any], Any], Encoder]]]:
        """The map's header and each field's packed key, getter and encoder: made on the first
        encode, since a plain tree (:func:`to_tree`) is never written as bytes."""
        return self.wire.map_header(len(self.names)), [
            (self.wire.pack(name), attrgetter(name), convert.encode)
            for name, convert in zip(self.names, self.converters, strict=True)]

    def encode(self, message: Any) -> bytes:
        header, writers = self.writers
        return header + b"".join([key + encode(get(message)) for key, get, encode in writers])

    def to_tree(self, message: Any) -> dict[str, Any]:
        return {name: tree(get(message)) for name, get, tree in self.trees}

    def decode(self, value: Any) -> Any:
        """The message a parsed tree describes; :class:`TreeError` when it describes none."""
        if type(value) is not dict:
            raise TreeError(f"expected a map of {self.name} fields, "
                            f"got {describe(value, self.wire)}")
        fields = {}
        for key, item in value.items():
            decode = self.decoders.get(key)
            if decode is None:
                exc = TreeError(f"unknown field of {self.name} "
                                f"(it has: {', '.join(self.decoders)})")
                exc.path.append(str(key))
                raise exc
            try:
                fields[key] = decode(item)
            except TreeError as exc:
                exc.path.append(key)
                raise
        return self.msg_type(**fields)  # fields left out keep the constructor's defaults

    def from_tree(self, value: Any) -> Any:
        """:meth:`decode`, its :class:`TreeError` told as a :class:`rosgate.CodecError` naming
        the field by its dotted path."""
        try:
            return self.decode(value)
        except TreeError as exc:
            where = f"{exc.where()}: " if exc.path else ""
            raise CodecError(f"{self.name}: {where}{exc.reason}") from None


# One converter tree per message class and format, shared by every codec instance; a Header is
# built once however many message types contain one.
_TREES: dict[tuple[type, WireFormat], MessageTree] = {}


def message_tree(msg_type: type, wire: WireFormat) -> MessageTree:
    tree = _TREES.get((msg_type, wire))
    if tree is None:
        tree = _TREES[msg_type, wire] = MessageTree(msg_type, wire)
    return tree


# -- plain Python trees, for formats with a library of their own (JSON) --------------------------

# What a field holding the wrong kind of value raises while packing; only a message filled with
# rclpy's field checks off (the default) can hold one.
_UNENCODABLE = (TypeError, ValueError, OverflowError, AttributeError, BufferError, struct.error)


def _never_written(value: Any) -> bytes:
    raise TypeError("a plain Python tree is not written as bytes")


# The plain values of to_tree and from_tree, described as a format that is never written: only
# its converters' tree and decode sides run, and its words name what a text parser returns.
_PLAIN = WireFormat(name="Python", pack=_never_written, float32_tag=0, float64_tag=0,
                    array_header=_never_written, map_header=_never_written,
                    bytes_header=_never_written, bytes_word="bytes", str_word="str",
                    nil_word="null")
_PLAIN_BASE64 = dataclasses.replace(_PLAIN, base64=True)


def to_tree(message: Any, *, base64: bool = False) -> dict[str, Any]:
    """``message`` as plain Python: a ``dict`` of its fields in .msg order, nested messages as
    dicts, arrays as lists, ``uint8[]``/``byte[]`` as ``bytes`` (``base64=True``: base64 text),
    numbers, strings and booleans as they are. :class:`rosgate.CodecError` for a field holding
    a value of the wrong kind, which only a message built with rclpy's field checks off can hold
    (``ROS_PYTHON_CHECK_FIELDS=1`` turns them on)."""
    tree = message_tree(type(message), _PLAIN_BASE64 if base64 else _PLAIN)
    try:
        return tree.to_tree(message)
    except _UNENCODABLE as exc:
        raise CodecError(f"cannot convert this {tree.name}: {exc}") from None


def from_tree(msg_type: type, tree: Any, *, base64: bool = False) -> Any:
    """The ``msg_type`` message that ``tree`` (plain Python, as :func:`to_tree` makes it and a
    text parser returns it) describes. Strict, because the tree comes from the network: an
    unknown field, a value of the wrong type, an integer out of range, a fixed array of the wrong
    length, a bounded sequence or string over its bound (and with ``base64=True``, byte fields
    that are not base64 text) raise :class:`rosgate.CodecError` naming the field by its dotted
    path (``pose.position.w``). Fields left out keep their defaults; an integer is taken for a
    float, a boolean never for a number."""
    return message_tree(msg_type, _PLAIN_BASE64 if base64 else _PLAIN).from_tree(tree)


# -- budgets for parsers -----------------------------------------------------------------------

#: below this many bytes a parser needs no budget: the most it can build is small
BUDGET_FROM = 1024


def container_budget(size: int) -> int:
    """The arrays and maps a parser may build from ``size`` bytes."""
    return size // 8 + 64


class OverBudget(ValueError):
    """A parser built more arrays and maps than its input's size allows."""


class ContainerBudget:
    """Counts the arrays and maps a parser builds (pass it as the parser's hook for each, it
    returns the value unchanged); :class:`OverBudget` past :func:`container_budget`."""

    __slots__ = ("left", "size")

    def __init__(self, size: int):
        self.size = size
        self.left = container_budget(size)

    def __call__(self, value: Any) -> Any:
        self.left -= 1
        if self.left < 0:
            raise OverBudget(f"more than {container_budget(self.size)} arrays and maps in "
                             f"{self.size} bytes")
        return value


# -- the codec base ---------------------------------------------------------------------------

class TreeCodec(Codec):
    """Base of codecs that write a message as a tree. A subclass sets ``name`` and ``wire`` and
    implements :meth:`parse`; it takes no options, unless it declares ``Options`` of its own."""

    wire: ClassVar[WireFormat]

    @dataclass(frozen=True)
    class Options:
        """None."""

    def __init__(self, msg_type: type, options: Any):
        super().__init__(msg_type, options)
        self.tree = message_tree(msg_type, self.wire)

    @abstractmethod
    def parse(self, data: bytes) -> Any:
        """``data`` as exactly one object of the format (dicts, lists, bytes, str, int, float,
        bool, None); :class:`rosgate.CodecError` when it is not."""

    def encode(self, message: Any) -> bytes:
        if type(message) is not self.msg_type:
            raise CodecError(f"expected a {self.tree.name} message, got {type(message).__name__}")
        try:
            return self.tree.encode(message)
        except _UNENCODABLE as exc:
            raise CodecError(f"cannot encode this {self.tree.name}: {exc}") from None

    def decode(self, data: bytes) -> Any:
        return self.tree.from_tree(self.parse(data))
