"""Serial datagrams: the framing the CVRA bridge wraps service requests in.

    frame = escape(payload) + escape(crc32(payload) as 4 bytes big-endian) + END

END (0xC0) ends a frame; inside one, 0xC0 is written ESC ESC_END (0xDB 0xDC) and 0xDB is
written ESC ESC_ESC (0xDB 0xDD), as in SLIP. The CRC is zlib's CRC-32 over the unescaped
payload. Vectors: plugins/mcu_cvra/tests/vectors/serial_datagram.txt (test_serial_datagram.py).

:class:`Decoder` is incremental: feed it what a connection gives, it yields whole payloads and
reports every frame it throws away (``bad_escape``, ``too_short``, ``bad_crc``, ``too_long``)
to ``on_error``; it never raises on input.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterator

from rosgate import Reason, declare

BAD_ESCAPE = declare("bad_escape", "a serial datagram with ESC followed by neither ESC_END nor "
                                   "ESC_ESC")
TOO_SHORT = declare("too_short", "a serial datagram shorter than its CRC")
BAD_CRC = declare("bad_crc", "a serial datagram whose CRC-32 does not match its payload")
TOO_LONG = declare("too_long", "a serial datagram longer than `max_request` without its end")

END, ESC, ESC_END, ESC_ESC = 0xC0, 0xDB, 0xDC, 0xDD
CRC_SIZE = 4
_ESCAPES = {ESC_END: END, ESC_ESC: ESC}


def escape(data: bytes) -> bytes:
    return data.replace(b"\xdb", b"\xdb\xdd").replace(b"\xc0", b"\xdb\xdc")


def encode(payload: bytes) -> bytes:
    return escape(payload + zlib.crc32(payload).to_bytes(CRC_SIZE, "big")) + bytes((END,))


class Decoder:
    """Cuts a byte stream into payloads. ``max_frame`` bounds a frame's unescaped size: a longer
    one is dropped (``too_long``) and skipped up to its END, so memory stays bounded."""

    def __init__(self, on_error: Callable[[Reason, str], None], max_frame: int = 64 * 1024):
        self.on_error = on_error  # (reason, detail)
        self.max_frame = max_frame
        self._frame = bytearray()
        self._escaped = False  # the previous byte was ESC
        self._skipping = False  # inside a frame already given up (too long or bad escape)

    def feed(self, data: bytes) -> Iterator[bytes]:
        for byte in data:  # per byte: requests are small, and escapes make slicing no simpler
            if byte == END:
                frame = self._end()
                if frame is not None:
                    yield frame
            elif self._skipping:
                continue
            elif self._escaped:
                self._escaped = False
                original = _ESCAPES.get(byte)
                if original is None:
                    self._give_up(BAD_ESCAPE, f"0xDB followed by 0x{byte:02X}")
                else:
                    self._append(original)
            elif byte == ESC:
                self._escaped = True
            else:
                self._append(byte)

    @property
    def pending(self) -> int:
        """Bytes of an unfinished frame held (0 between frames)."""
        return len(self._frame)

    def _append(self, byte: int) -> None:
        if len(self._frame) >= self.max_frame + CRC_SIZE:
            self._give_up(TOO_LONG, f"over {self.max_frame} bytes without an end")
        else:
            self._frame.append(byte)

    def _give_up(self, reason: Reason, detail: str) -> None:
        self.on_error(reason, detail)
        self._frame.clear()
        self._escaped = False
        self._skipping = True

    def _end(self) -> bytes | None:
        frame, escaped, skipping = bytes(self._frame), self._escaped, self._skipping
        self._frame.clear()
        self._escaped = self._skipping = False
        if skipping:
            return None
        if escaped:
            self.on_error(BAD_ESCAPE, "0xDB followed by the end of the frame")
            return None
        if len(frame) < CRC_SIZE:
            self.on_error(TOO_SHORT, f"{len(frame)} bytes before the end, a CRC alone takes 4")
            return None
        payload, crc = frame[:-CRC_SIZE], int.from_bytes(frame[-CRC_SIZE:], "big")
        if zlib.crc32(payload) != crc:
            self.on_error(BAD_CRC, f"CRC 0x{crc:08X}, payload's is 0x{zlib.crc32(payload):08X}")
            return None
        return payload
