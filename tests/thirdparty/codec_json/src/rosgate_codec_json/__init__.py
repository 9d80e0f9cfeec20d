"""rosgate codec ``json``: a ROS message as a JSON object, for peers that read JSON (a web page,
a script, a log). A complete codec plugin in one page.

The mapping is rosgate's tree mapping (:mod:`rosgate_message_tree`): a message is an object of
its fields in .msg order, nested messages are objects, arrays are arrays, numbers, strings and
booleans are themselves, ``builtin_interfaces/Time`` is ``{"sec": ..., "nanosec": ...}``. JSON has
no byte strings, so ``uint8[]`` and ``byte[]`` fields (an image's pixels) are base64 text. Floats
that are not numbers are written ``NaN``, ``Infinity`` and ``-Infinity``, as Python's and most
JSON libraries read them (strict JSON has no way to write them).

Decoding is strict, because the bytes come from the network: anything but one JSON value in
UTF-8, or a value that does not fit the message (an unknown field, a value of the wrong type or
range, a fixed array of the wrong length, base64 that is not) is a :class:`rosgate.CodecError`
naming the field by its dotted path (``pose.position.w``). Fields left out keep their defaults.

Options (``plugins: {json: {...}}``): see :class:`JsonCodec.Options`, or
``rosgate plugins --options json``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rosgate_message_tree import from_tree, to_tree

from rosgate import Codec, CodecError, hookimpl, option


class JsonCodec(Codec):
    """ROS messages as JSON objects; the module documentation has the mapping."""

    name = "json"

    @dataclass(frozen=True)
    class Options:
        indent: int | None = option(None, "spaces to indent nested values by; null: one line",
                                    minimum=0, maximum=8)
        ascii: bool = option(True, "escape every non-ASCII character (\\u00e9); false: UTF-8")

    options: Options

    def encode(self, message: Any) -> bytes:
        if type(message) is not self.msg_type:
            raise CodecError(f"expected a {self.msg_type.__name__} message, "
                             f"got {type(message).__name__}")
        indent = self.options.indent
        return json.dumps(to_tree(message, base64=True), indent=indent,
                          ensure_ascii=self.options.ascii,
                          separators=(",", ": ") if indent is not None else (",", ":")).encode()

    def decode(self, data: bytes) -> Any:
        try:
            tree = json.loads(data)
        except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError
            raise CodecError(f"not one JSON value: {exc}") from None
        return from_tree(self.msg_type, tree, base64=True)


@hookimpl
def rosgate_codecs(register: Callable[[type[Codec]], None]) -> None:
    register(JsonCodec)
