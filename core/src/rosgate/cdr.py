"""A quick look at serialized CDR, written from the message's definition: ``True`` when the bytes
are certainly a well-formed message of the type, ``False`` when they may not be — then the
middleware's deserializer decides (:func:`rosgate.ros.cdr_checker`), which costs ~15 µs per
message cold in a bridge against a handful of ``struct`` reads here.

It checks (XCDR1, either byte order) the encapsulation header; every primitive in bounds at its
alignment (at most 8, counted from the end of the 4-byte header); booleans 0 or 1; strings as a
``u32`` length of at least 1 whose last byte is a NUL; sequences as a ``u32`` count, then their
elements; fixed arrays; nested messages. Bounded strings and sequences, wide strings and ``long
double`` make :func:`walker` return None (the middleware judges every frame). Anything unexpected
is ``False``: a ``True`` must never be given to bytes the middleware refuses
(tests/test_cdr_walker.py holds it to that on mutated messages of many types).
"""

from __future__ import annotations

import importlib
import struct
from collections.abc import Callable
from typing import Any

from rosidl_parser import definition as idl

#: (data, position) -> the position after the field; raises _Bad when it cannot be read
Step = Callable[[bytes, int], int]

_HEADER = 4  # the encapsulation header: alignment counts from its end
_SIZES = {"boolean": 1, "octet": 1, "char": 1, "uint8": 1, "int8": 1, "uint16": 2, "int16": 2,
          "uint32": 4, "int32": 4, "uint64": 8, "int64": 8, "float": 4, "double": 8}
_BOOLS = b"\x00\x01"


class _Bad(Exception):
    """Not certainly well-formed."""


class _Unsupported(Exception):
    """A field this walker does not judge (the middleware does)."""


def _align(position: int, size: int) -> int:
    return position + (-(position - _HEADER) % size)


class _Walker:
    """The steps of one type in one byte order."""

    def __init__(self, little: bool):
        self.u32 = struct.Struct("<I" if little else ">I").unpack_from
        self.cache: dict[tuple[str, ...], list[Step]] = {}

    def message(self, msg_type: type) -> list[Step]:
        key = (msg_type.__module__, msg_type.__name__)
        if key not in self.cache:
            self.cache[key] = []  # a type that contains itself is not a ROS message
            self.cache[key] = self._fields(msg_type)
        return self.cache[key]

    def _fields(self, msg_type: type) -> list[Step]:
        slots = msg_type.SLOT_TYPES  # type: ignore[attr-defined]
        if not slots:  # an empty message: its C struct has one uint8 member, and so has its CDR
            return [_Skip(1, 1)]
        return _fuse([self.field(t) for t in slots])

    def field(self, t: idl.AbstractType) -> Step:
        if isinstance(t, idl.BasicType):
            return self._basic(t.typename)
        if isinstance(t, idl.UnboundedString):
            return self._string
        if isinstance(t, idl.NamespacedType):
            nested = getattr(importlib.import_module(".".join(t.namespaces)), t.name)
            return self._nested(self.message(nested))
        if isinstance(t, idl.Array):
            return self._array(t.value_type, t.size)
        if isinstance(t, idl.UnboundedSequence):
            return self._sequence(t.value_type)
        raise _Unsupported(type(t).__name__)

    # -- the steps ---------------------------------------------------------------------------
    @staticmethod
    def _basic(typename: str) -> Step:
        size = _SIZES.get(typename)
        if size is None:
            raise _Unsupported(typename)
        if typename == "boolean":
            def boolean(data: bytes, at: int) -> int:
                if at >= len(data) or data[at] > 1:
                    raise _Bad
                return at + 1
            return boolean
        return _Skip(size, size)

    def _string(self, data: bytes, at: int) -> int:
        at = _align(at, 4)
        if at + 4 > len(data):
            raise _Bad
        (n,) = self.u32(data, at)
        end = at + 4 + n
        if n < 1 or end > len(data) or data[end - 1] != 0:
            raise _Bad
        return end

    @staticmethod
    def _nested(steps: list[Step]) -> Step:
        if len(steps) == 1 and isinstance(steps[0], _Skip):
            return steps[0]  # a Vector3, a Time: CDR gives a nested message no alignment of its own

        def nested(data: bytes, at: int) -> int:
            for step in steps:
                at = step(data, at)
            return at
        return nested

    def _array(self, value_type: idl.AbstractType, count: int) -> Step:
        element = self.field(value_type)
        if isinstance(element, _Skip):
            return _Skip(element.align, element.size * count)
        if isinstance(value_type, idl.BasicType) and value_type.typename == "boolean":
            return _bools_fixed(count)
        return self._nested([element] * count)

    def _sequence(self, value_type: idl.AbstractType) -> Step:
        element = self.field(value_type)
        u32 = self.u32
        boolean = isinstance(value_type, idl.BasicType) and value_type.typename == "boolean"
        size, align = (element.size, element.align) if isinstance(element, _Skip) else (0, 1)

        def sequence(data: bytes, at: int) -> int:
            at = _align(at, 4)
            if at + 4 > len(data):
                raise _Bad
            (n,) = u32(data, at)
            at += 4
            if size:  # primitives: one bounds check for all of them
                aligned = _align(at, align)
                if aligned > len(data):  # the padding must be there, even before no element
                    raise _Bad
                if n:
                    at = aligned
                end = at + n * size
                if end > len(data):
                    raise _Bad
                if boolean and data[at:end].translate(None, _BOOLS):
                    raise _Bad
                return end
            if n > len(data) - at:  # every element takes a byte at least
                raise _Bad
            for _ in range(n):
                at = element(data, at)
            return at
        return sequence


class _Skip:
    """A run of primitives of one alignment whose values are all valid: only its bounds matter."""

    __slots__ = ("align", "size")

    def __init__(self, align: int, size: int):
        self.align = min(align, 8)
        self.size = size

    def __call__(self, data: bytes, at: int) -> int:
        end = _align(at, self.align) + self.size
        if end > len(data):
            raise _Bad
        return end


def _bools_fixed(count: int) -> Step:
    def bools(data: bytes, at: int) -> int:
        end = at + count
        if end > len(data) or data[at:end].translate(None, _BOOLS):
            raise _Bad
        return end
    return bools


def _fuse(steps: list[Step]) -> list[Step]:
    """Neighbouring primitives of one size become one step (an Image's header, a Twist)."""
    out: list[Step] = []
    for step in steps:
        last = out[-1] if out else None
        if (isinstance(step, _Skip) and isinstance(last, _Skip) and last.align == step.align
                and last.size % last.align == 0):
            out[-1] = _Skip(last.align, last.size + step.size)
        else:
            out.append(step)
    return out


def walker(msg_type: type) -> Callable[[bytes | bytearray], bool] | None:
    """The quick look for ``msg_type`` (see the module's docstring), or None when the type has a
    field it does not judge."""
    try:  # by the encapsulation's second byte: 1 little-endian, 0 big-endian
        orders = {1: _Walker(True).message(msg_type), 0: _Walker(False).message(msg_type)}
    except (_Unsupported, AttributeError, ImportError):
        return None

    def well_formed(data: bytes | bytearray) -> bool:
        if len(data) < _HEADER or data[0] != 0:
            return False
        steps: Any = orders.get(data[1])
        if steps is None:
            return False
        at = _HEADER
        try:
            for step in steps:
                at = step(data, at)
        except _Bad:
            return False
        return True

    return well_formed
