"""ROS's own interface test set (``test_msgs``) as a corpus: every message type, filled with
values at the edges of each field kind, and a field-by-field comparison that tells -0.0 from 0.0
and NaN from NaN.

Values are built from each type's field declarations (``get_fields_and_field_types``), so a type
``test_msgs`` gains later is covered without a change here. Three variants per type:

- ``low``: the smallest value of every kind (integer minimums, -FLT_MAX, -DBL_MAX, ``False``,
  empty strings, empty unbounded sequences, bounded sequences at their bound);
- ``high``: the largest (integer maximums, FLT_MAX, DBL_MAX, long and non-ASCII strings, bounded
  strings at their bound, unbounded sequences of several elements);
- ``special``: -0.0, infinities, NaN, the smallest subnormals, astral-plane characters.
"""

from __future__ import annotations

import importlib
import math
import re
import struct
import sys
from collections.abc import Iterator
from typing import Any

import numpy

PACKAGE = "test_msgs"
VARIANTS = ("low", "high", "special")

FLT_MAX = struct.unpack("<f", b"\xff\xff\x7f\x7f")[0]       # 3.4028234663852886e+38
FLT_TRUE_MIN = struct.unpack("<f", b"\x01\x00\x00\x00")[0]  # the smallest subnormal float32
DBL_MAX = sys.float_info.max

INTEGERS = {
    "int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1), "char": (0, 2**8 - 1),
    "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
    "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1),
}
TEXT = {"low": "", "high": "Grüße, ROS ✓ 日本語 " + "x" * 4000, "special": "🤖 \u00e9\u0301 \t\n"}
WTEXT = {"low": "", "high": "Grüße ✓ 日本語 " + "w" * 500, "special": "🤖 wide ✓"}

_DECL = re.compile(r"^(?:sequence<(?P<seq>.+?)(?:, (?P<seqbound>\d+))?>|(?P<elem>[^\[]+)"
                   r"(?:\[(?P<size>\d+)\])?)$")


def types(package: str = PACKAGE) -> list[type]:
    """Every message class of ``package``, by name."""
    module = importlib.import_module(f"{package}.msg")
    return [getattr(module, n) for n in sorted(dir(module))
            if n[:1].isupper() and hasattr(getattr(module, n), "get_fields_and_field_types")]


def corpus(package: str = PACKAGE) -> Iterator[tuple[str, str, Any]]:
    """``(type name, variant, message)`` for every type and variant."""
    for cls in types(package):
        for variant in VARIANTS:
            yield f"{package}/msg/{cls.__name__}", variant, fill(cls, variant)


def fill(cls: type, variant: str) -> Any:
    message = cls()
    for field, declaration in cls.get_fields_and_field_types().items():
        setattr(message, field, _value(declaration, variant))
    return message


def _value(declaration: str, variant: str) -> Any:
    match = _DECL.match(declaration)
    assert match, declaration
    if match["seq"]:
        bound = int(match["seqbound"]) if match["seqbound"] else None
        count = bound if bound is not None else {"low": 0, "high": 5, "special": 2}[variant]
        return _many(match["seq"], count, variant)
    if match["size"]:
        return _many(match["elem"], int(match["size"]), variant)
    return _one(match["elem"], variant)


def _many(element: str, count: int, variant: str) -> Any:
    values = [_one(element, variant, i) for i in range(count)]
    if element in ("float", "double") or element in INTEGERS:
        dtype = {"float": numpy.float32, "double": numpy.float64}.get(element, element)
        if element == "char":
            dtype = numpy.uint8
        return numpy.array(values, dtype=dtype) if values else numpy.array([], dtype=dtype)
    return values


def _one(kind: str, variant: str, index: int = 0) -> Any:
    if kind == "boolean":
        return variant != "low" if index % 2 == 0 else variant == "low"
    if kind == "octet":
        return bytes([{"low": 0, "high": 255, "special": 0x80}[variant] ^ index])
    if kind in INTEGERS:
        low, high = INTEGERS[kind]
        return {"low": low + index, "high": high - index, "special": (low + high) // 2}[variant]
    if kind in ("float", "double"):
        biggest, tiniest = (FLT_MAX, FLT_TRUE_MIN) if kind == "float" else \
            (DBL_MAX, 5e-324)
        specials = [-0.0, math.inf, -math.inf, math.nan, tiniest, -tiniest]
        return {"low": -biggest, "high": biggest,
                "special": specials[index % len(specials)]}[variant]
    bounded = re.match(r"^(w?string)<(\d+)>$", kind)
    if bounded:
        bound = int(bounded[2])
        text = (WTEXT if bounded[1] == "wstring" else TEXT)[variant]
        return (text * (bound // max(1, len(text)) + 1))[:bound] if text else ""
    if kind == "string":
        return TEXT[variant] + (str(index) if index else "")
    if kind == "wstring":
        return WTEXT[variant] + (str(index) if index else "")
    package, name = kind.split("/")
    cls = getattr(importlib.import_module(f"{package}.msg"), name)
    return fill(cls, variant)


def differences(expected: Any, actual: Any, path: str = "") -> list[str]:
    """Where two messages (or values) differ, one line per field; empty when they are the same
    to the bit: -0.0 is not 0.0, NaN equals NaN, a float32 compares as a float32."""
    if hasattr(expected, "get_fields_and_field_types"):
        if type(expected) is not type(actual):
            return [f"{path or '.'}: {type(actual).__name__} instead of {type(expected).__name__}"]
        found: list[str] = []
        for field in expected.get_fields_and_field_types():
            found += differences(getattr(expected, field), getattr(actual, field),
                                 f"{path}.{field}" if path else field)
        return found
    if isinstance(expected, (list, tuple, numpy.ndarray)) and not isinstance(expected, str):
        if not isinstance(actual, (list, tuple, numpy.ndarray)) or len(actual) != len(expected):
            return [f"{path}: {_show(actual)} instead of {_show(expected)}"]
        found = []
        for i, (e, a) in enumerate(zip(expected, actual, strict=True)):
            found += differences(e, a, f"{path}[{i}]")
        return found
    if isinstance(expected, (float, numpy.floating)):
        if not isinstance(actual, (float, numpy.floating)) or not _same_float(expected, actual):
            return [f"{path}: {_show(actual)} instead of {_show(expected)}"]
        return []
    if isinstance(expected, (bool, numpy.bool_)):
        same = isinstance(actual, (bool, numpy.bool_)) and bool(actual) == bool(expected)
        return [] if same else [f"{path}: {_show(actual)} instead of {_show(expected)}"]
    integers = (int, numpy.integer)
    if type(expected) is not type(actual) and not (
            isinstance(expected, integers) and isinstance(actual, integers)):
        return [f"{path}: {_show(actual)} instead of {_show(expected)}"]
    return [] if expected == actual else [f"{path}: {_show(actual)} instead of {_show(expected)}"]


def _same_float(a: Any, b: Any) -> bool:
    a, b = float(a), float(b)
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return a == b and math.copysign(1, a) == math.copysign(1, b)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
