"""The ``zstd`` payload transform: a topic's payloads compressed, between the codec and the cipher.

A transmitting topic with ``compression: zstd`` compresses every payload (a zstd frame, which
states its decompressed size) at ``level`` (``plugins: {zstd: {level: 3}}``, or per topic
``compression: {zstd: {level: 19}}``) and sends the result when it is smaller, after its wire id
(1), with the envelope's ``FLAG_COMPRESSED`` set; a payload that does not shrink (an image of
noise, a tiny message) goes as it was, flag clear. The flag travels in the envelope header, which
every cipher authenticates, so a receiver decompresses exactly what the sender compressed,
whatever its own file says (see :mod:`rosgate.transform`).

A hostile sender (anyone who reaches a port without a cipher) can make a small frame that
claims to decompress into a huge one. :meth:`Decompressor.decompress` therefore refuses a frame
that does not state its size, or states more than ``limit`` — the most a frame may have on a
link (64 MiB), so compression lets no message be larger than it could be uncompressed — before
it allocates anything.

Compressing before sealing lets someone who can put chosen bytes into a topic and watch frame
sizes learn about the rest of that message (CRIME, BREACH): do not compress a topic that mixes
secrets with data an attacker controls.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from rosgate import OptionError, Transform, TransformError, hookimpl, option

#: zstd's magic number, the first 4 bytes of every frame (little-endian 0xFD2FB528)
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


class CompressionError(TransformError):
    """A payload that cannot be decompressed within the bound (counted ``decompression_error``)."""


def _zstd() -> Any:
    import zstandard  # a C extension: imported with the first compressing route

    return zstandard


class Compressor:
    """zstd at one level for one route. Thread-safe: a route may be called from several
    executor threads, and a zstd context serves one at a time."""

    def __init__(self, level: int):
        zstd = _zstd()
        self.level = level
        self._context = zstd.ZstdCompressor(level=level, write_content_size=True)
        self._lock = threading.Lock()

    def compress(self, payload: bytes) -> bytes | None:
        """``payload`` compressed, or None when that would not make it smaller."""
        with self._lock:
            packed = self._context.compress(payload)
        return packed if len(packed) < len(payload) else None


class Decompressor:
    """Decompresses what a sender compressed, never beyond ``limit`` bytes."""

    def __init__(self, limit: int):
        self.limit = limit
        self._context: Any = None
        self._lock = threading.Lock()

    def decompress(self, data: bytes) -> bytes:
        zstd = _zstd()
        if data[:4] != ZSTD_MAGIC:
            raise CompressionError("not a zstd frame")
        try:
            size = zstd.frame_content_size(data)
        except zstd.ZstdError as exc:
            raise CompressionError(f"a zstd frame with a bad header: {exc}") from None
        # zstandard's max_output_size does not bound a frame that states its size: check first
        if size < 0:
            raise CompressionError("a zstd frame that does not state its size")
        if size > self.limit:
            raise CompressionError(f"a zstd frame that would decompress to {size} bytes, over "
                                   f"the limit of {self.limit}")
        with self._lock:
            if self._context is None:
                self._context = zstd.ZstdDecompressor()
            try:
                out = self._context.decompress(data, max_output_size=self.limit)
            except zstd.ZstdError as exc:
                raise CompressionError(f"zstd: {exc}") from None
        if len(out) != size:
            raise CompressionError(f"a zstd frame of {len(out)} bytes that stated {size}")
        return out


class ZstdTransform(Transform):
    """zstd compression; payloads it does not shrink go as they are."""

    name = "zstd"
    wire_id = 1

    @dataclass(frozen=True)
    class Options:
        level: int = option(3, "zstd's level: 1 (fastest) to 22 (smallest), -7 to -1 faster "
                               "still; 3, zstd's own default, is fast and gets most of the gain",
                            minimum=-7, maximum=22)

        def __post_init__(self) -> None:
            if self.level == 0:
                raise OptionError("level", "must not be 0 (zstd would take it for its default, 3)",
                                  "level: 3, or -7..-1 for faster, 1..22 for smaller")

    def __init__(self, options: Any, limit: int):
        super().__init__(options, limit)
        self.compressor = Compressor(self.options.level)
        self.decompressor = Decompressor(limit)

    def encode(self, payload: bytes) -> bytes | None:
        return self.compressor.compress(payload)

    def decode(self, data: bytes) -> bytes:
        return self.decompressor.decompress(data)


@hookimpl
def rosgate_transforms(register: Any) -> None:
    register(ZstdTransform)
