"""A payload transform: zlib's deflate, from the standard library."""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

from rosgate import Transform, TransformError, hookimpl, option


class DeflateTransform(Transform):
    """deflate; a payload it does not shrink goes as it is."""

    name = "deflate"
    wire_id = 2  # the byte in front of what it made: unique among installed transforms

    @dataclass(frozen=True)
    class Options:
        level: int = option(6, "zlib's level: 1 (fastest) to 9 (smallest)", minimum=1, maximum=9)

    def encode(self, payload: bytes) -> bytes | None:
        packed = zlib.compress(payload, self.options.level)
        return packed if len(packed) < len(payload) else None

    def decode(self, data: bytes) -> bytes:
        inflater = zlib.decompressobj()
        try:  # never more than one byte past the limit, whatever the stream claims
            out = inflater.decompress(data, self.limit + 1)
        except zlib.error as exc:
            raise TransformError(f"deflate: {exc}") from None
        if len(out) > self.limit:
            raise TransformError(f"inflates to more than {self.limit} bytes")
        if not inflater.eof or inflater.unused_data:
            raise TransformError("not one whole deflate stream")
        return out


@hookimpl
def rosgate_transforms(register: Any) -> None:
    register(DeflateTransform)
