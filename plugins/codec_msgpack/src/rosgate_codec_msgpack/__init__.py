"""rosgate codec ``msgpack``: a ROS message as a MessagePack map, for peers without ROS.

This is the wire format of the CVRA MessagePack bridge: a microcontroller with a small
MessagePack library reads and writes it without knowing anything about ROS or CDR.

Wire mapping: the tree mapping of :mod:`rosgate_message_tree` (shared with the ``cbor``
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

What a peer sends need not be a map. Any MessagePack value is taken for a message (or a
service's request or answer), as a microcontroller's firmware sends it:

* a map: fields by name, as above;
* an array: fields in .msg order (``[1.5, 2.0]`` is a Pose2D's ``x`` and ``y``); more elements
  than the message has fields is an error;
* nil: the message with every field at its default;
* a single value (bool, number, str, bin): the message's first field that can hold it — a bool
  the first ``bool`` field, a number the first numeric field, a str the first string field, bin
  the first ``uint8[]``/``byte[]`` field (a bare float is a ``std_msgs/Float32``'s ``data``, a
  ``Pose2D``'s ``x``); a value no field can hold is an error;
* on a service's answer (a ``*_Response``), nil or a single value that is not a bool also sets a
  ``bool success`` field to true: the server ran the call (so "pong" answers a
  ``std_srvs/Trigger`` with ``success: true, message: "pong"``).

Any float width is taken for any float field, and an integer too. Decoding is otherwise strict,
because the bytes come from the network: anything but exactly one MessagePack object, a map key
that is not a str, an ext type (timestamps included), or a tree that does not fit the message
(see :mod:`rosgate_message_tree`) is a :class:`rosgate.CodecError` naming the field by its
dotted path (``pose.position.w``, ``points[3].x``). Nothing is longer than the input, and the
parser builds at most one array or map per 8 bytes of it
(:func:`rosgate_message_tree.container_budget`): 4 MB of empty maps is refused, not 277 MB.

Framing ``none`` and ``serial_datagram`` (the microcontroller profile): the core writes and
reads the entry's name in front of the codec's bytes (``messagepack = True`` says it may), and
sets the two options below from the entry's own ``args:`` and ``floats:`` keys.

Options (``plugins: msgpack:``, for entries with an envelope; a microcontroller entry's own keys
win):

* ``args``: ``map`` (default) writes the fields by name; ``array`` writes them in .msg order;
  ``value`` writes the first field's value alone (nil for a message without fields).
* ``floats``: ``float64`` (default) keeps ``float64`` fields 64 bits wide; ``float32`` writes every
  float as a MessagePack float 32, as a microcontroller's firmware does.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import msgpack
from rosgate_message_tree import (
    BUDGET_FROM,
    ContainerBudget,
    TreeCodec,
    TreeError,
    WireFormat,
    describe,
    message_tree,
)
from rosidl_parser import definition as idl

import rosgate

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
MESSAGEPACK_FLOAT32 = dataclasses.replace(MESSAGEPACK, float64_as_float32=True)
NIL = b"\xc0"


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
    """ROS messages as MessagePack; the module documentation has the mapping."""

    name = "msgpack"
    messagepack = True
    wire = MESSAGEPACK

    @dataclass(frozen=True)
    class Options:
        args: Literal["map", "array", "value"] = rosgate.option(
            "map", "how a message is written: map (fields by name), array (fields in .msg "
                   "order) or value (the first field alone)")
        floats: Literal["float64", "float32"] = rosgate.option(
            "float64", "float32: write float64 fields as MessagePack float 32, as a "
                       "microcontroller does")

    def __init__(self, msg_type: type, options: Any):
        super().__init__(msg_type, options)
        if self.options.floats == "float32":
            self.tree = message_tree(msg_type, MESSAGEPACK_FLOAT32)
        self._write = {"map": self.tree.encode, "array": self._array,
                       "value": self._value}[self.options.args]
        self._takers = _takers(msg_type)
        self._fields = list(self.tree.names)
        self._answer = msg_type.__name__.endswith("_Response") and \
            self._takers.get(bool) == "success"

    def encode(self, message: Any) -> bytes:
        if self.options.args == "map" or type(message) is not self.msg_type:
            return super().encode(message)
        try:
            return self._write(message)
        except _UNWRITABLE as exc:
            raise rosgate.CodecError(f"cannot encode this {self.tree.name}: {exc}") from None

    def _array(self, message: Any) -> bytes:
        _, writers = self.tree.writers
        return MESSAGEPACK.array_header(len(writers)) + b"".join(
            [encode(get(message)) for _, get, encode in writers])

    def _value(self, message: Any) -> bytes:
        _, writers = self.tree.writers
        if not writers:
            return NIL
        _, get, encode = writers[0]
        return encode(get(message))

    def decode(self, data: bytes) -> Any:
        value = self.parse(data)
        if type(value) is not dict:
            value = self._as_fields(value)
        return self.tree.from_tree(value)

    def _as_fields(self, value: Any) -> dict[str, Any]:
        """A value other than a map, as the map of fields it stands for (the module
        documentation has the rules)."""
        if type(value) is list:
            if len(value) > len(self._fields):
                raise rosgate.CodecError(
                    f"{self.tree.name}: [{len(self._fields)}]: an array of {len(value)} values "
                    f"for {len(self._fields)} fields ({', '.join(self._fields) or 'none'})")
            return dict(zip(self._fields, value, strict=False))
        fields: dict[str, Any] = {}
        if value is not None:
            field = self._takers.get(type(value))
            if field is None:
                raise rosgate.CodecError(
                    f"{self.tree.name}: no field takes {describe(value, self.wire)} (it has: "
                    f"{', '.join(self._fields) or 'no fields'})")
            fields[field] = value
        if self._answer and type(value) is not bool:
            fields["success"] = True
        return fields

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


# What a field holding the wrong kind of value raises while packing (only a message built with
# rclpy's field checks off can hold one), or a float64 past float32's range written as float32.
_UNWRITABLE = (TypeError, ValueError, OverflowError, AttributeError, struct.error, TreeError)

_NUMBERS = {"float", "double", "octet", "int8", "uint8", "int16", "uint16", "int32", "uint32",
            "int64", "uint64"}


def _takers(msg_type: Any) -> dict[type, str]:
    """For each kind of single value, the first field of ``msg_type`` that can hold it."""
    takers: dict[type, str] = {}
    for name, slot in zip(msg_type.get_fields_and_field_types(), msg_type.SLOT_TYPES,
                          strict=True):
        kinds: tuple[type, ...] = ()
        if isinstance(slot, idl.BasicType):
            kinds = (bool,) if slot.typename == "boolean" else \
                (int, float) if slot.typename in _NUMBERS else ()
        elif isinstance(slot, idl.AbstractGenericString):
            kinds = (str,)
        elif isinstance(slot, idl.AbstractNestedType) and \
                isinstance(slot.value_type, idl.BasicType) and \
                slot.value_type.typename in ("uint8", "octet"):
            kinds = (bytes,)
        for kind in kinds:
            takers.setdefault(kind, name)
    return takers


@rosgate.hookimpl
def rosgate_codecs(register: Callable[[type[rosgate.Codec]], None]) -> None:
    register(MsgpackCodec)
