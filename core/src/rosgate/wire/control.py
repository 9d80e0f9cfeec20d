"""Control messages: the JSON bodies of the main line's frames (``hello``, ``welcome``, ``ping``,
``bye`` ...), read within bounds (:func:`parse`), because they come from peers not yet trusted.
"""

from __future__ import annotations

import json
import re
from typing import Any

MAX_SIZE = 1024 * 1024
MAX_DEPTH = 32

_STRINGS = re.compile(rb'"(?:[^"\\]++|\\.)*+"', re.S)
_PAIRS = re.compile(rb"\[\]|\{\}")
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


class ControlError(ValueError):
    """A control message that is not one (or not within bounds)."""


def _refuse_constant(name: str) -> Any:
    raise ControlError(f"{name} is not a number a control message may carry")


def too_deep(data: bytes, limit: int = MAX_DEPTH) -> bool:
    """Whether arrays and objects in JSON text ``data`` nest deeper than ``limit`` (or do not
    balance). Strings are taken out, then the brackets alone, innermost pairs first, ``limit``
    times: each pass is one regular expression in C, and nothing recurses."""
    brackets = _STRINGS.sub(b"", data).translate(None, _NOT_BRACKETS)
    for _ in range(limit):
        if not brackets:
            return False
        fewer = _PAIRS.sub(b"", brackets)
        if len(fewer) == len(brackets):
            return True  # unbalanced: no JSON parser would take it either
        brackets = fewer
    return bool(brackets)


def parse(data: bytes) -> dict[str, Any]:
    """The JSON object in ``data``: at most :data:`MAX_SIZE` bytes of UTF-8, nested at most
    :data:`MAX_DEPTH` deep (a ROS entry in a hello needs 4), no ``NaN`` or ``Infinity``; else
    :class:`ControlError` saying why, never another exception."""
    if len(data) > MAX_SIZE:
        raise ControlError(f"{len(data)} bytes, more than {MAX_SIZE}")
    if too_deep(data):
        raise ControlError(f"nested deeper than {MAX_DEPTH}")
    try:
        message = json.loads(data.decode("utf-8"), parse_constant=_refuse_constant)
    except ControlError:
        raise
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise ControlError(f"not JSON: {exc}") from None
    if not isinstance(message, dict):
        raise ControlError(f"a JSON {type(message).__name__}, not an object")
    return message
