"""rosgate transport ``serial``: a serial line — a UART, a USB-CDC port, a telemetry radio in
transparent mode — as a datagram link.

The line carries bytes; frames are cut out of it by serial-datagram framing (SLIP-style escapes
and a CRC-32 per frame, ``rosgate_mcu_cvra.serial_datagram``, the framing CVRA's firmware
speaks). A frame whose CRC fails, whose escape is broken or that runs past ``max_frame`` is
dropped and counted (``bad_crc``, ``bad_escape``, ``too_short``, ``too_long``), and the reader
starts again at the next delimiter: nothing on the line is assumed reliable. The core does the
rest, as on any datagram link: frames over ``max_frame`` are cut (below 256 bytes by the compact
packetizer), loss recovery (``recovery:``) and priorities apply.

Wire format (``multiplex: true``, the default), one serial datagram per frame::

    escape(destination port (2 bytes, big-endian) + source port (2) + frame + CRC-32 (4)) + 0xC0

so every entry of a bridge shares the one line, each at its ``port:``, as on UDP; a receive
reports ``(device, source port)``, which ``send`` answers. ``multiplex: false`` sends the frame
alone in its serial datagram, as a microcontroller speaking CVRA's layouts expects: every
entry bound to a port then receives every datagram.

Addresses: the device is the option ``device`` (one line per bridge); the host of an address
(``bridge.peer``, ``bridge.listen``) is only a name, replaced by the device (``check_address``),
so that a frame's source is the very address its answers were sent to: loss recovery's
acknowledgements then find the frames they acknowledge. Port 0 binds a sender, given a port of
its own from 49152 up so that answers reach it.

Unplugged: when the device vanishes (a USB adapter pulled, a radio power-cycled), the line logs
it once, tells every endpoint's link its line is gone (``watch_line``: the core holds reliable
topics' frames until it is back and drops best-effort ones), refuses what is still sent
(``OSError``), and opens the device again by its name as soon as it is back — name it by its
stable ``/dev/serial/by-id/...`` link, which follows it to whatever ``ttyUSB`` number it comes
back as — and then tells the links it is back.

Capacity: a byte on the line takes a start bit, 8 data bits, the parity bit if any and the
stop bits, so ``baud`` gives the bits per second of frames the line carries; 95 % of that is
:attr:`SerialTransport.bandwidth`, the budget of the link when ``bridge.links`` names none.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from rosgate_mcu_cvra import serial_datagram

from rosgate import Address, DatagramTransport, LinkError, OptionError, hookimpl, option

if importlib.util.find_spec("serial") is None:  # imported where a port is opened
    raise ModuleNotFoundError("No module named 'serial' (pip install pyserial)", name="serial")

log = logging.getLogger("rosgate.serial")

#: destination and source port in front of each multiplexed frame
PORTS_SIZE = 4
#: the bytes every frame costs on the line besides itself: the ports, the CRC, the delimiter
#: (escapes add one byte per 0xC0 or 0xDB: 1 in 128 of random bytes)
OVERHEAD = PORTS_SIZE + serial_datagram.CRC_SIZE + 1
#: the first port a sender bound at port 0 is given
EPHEMERAL = 49152
#: the share of the line the link's budget takes: a little below what the line carries, so
#: that a backlog waits in the bridge, where priorities order it, and not in the port's buffer
#: (escapes, uncounted, take about 1 %)
SHARE = 0.95
#: seconds between looks for a device that vanished, and the reader's wait per read
POLL = 0.05

DropCallback = Callable[[Any, str], None]


class SerialTransport(DatagramTransport):
    name = "serial"
    packet_overhead = OVERHEAD
    one_line = True  # every port shares the line's budget

    @dataclass(frozen=True)
    class Options:
        device: str = option(doc="the serial port: a stable /dev/serial/by-id/... name, or "
                                 "/dev/ttyUSB0, /dev/ttyACM0, /dev/ttyAMA0")
        baud: int = option(115200, "the line's speed, bits per second", minimum=50)
        parity: Literal["none", "even", "odd", "mark", "space"] = option(
            "none", "the parity bit of each byte")
        stop_bits: float = option(1, "stop bits of each byte: 1, 1.5 or 2")
        flow_control: Literal["none", "rtscts", "xonxoff"] = option(
            "none", "rtscts: hardware flow control (RTS/CTS lines); xonxoff is refused")
        max_frame: int = option(250, "the longest frame on the line, bytes (radios lose long "
                                     "ones); the core cuts longer messages",
                                minimum=16, maximum=65_000)
        multiplex: bool = option(True, "every frame names its ports, so entries share the "
                                       "line; false: bare serial datagrams (a microcontroller)")

        def __post_init__(self) -> None:
            if self.stop_bits not in (1, 1.5, 2):
                raise OptionError("stop_bits", f"must be 1, 1.5 or 2, not {self.stop_bits!r}")
            if self.flow_control == "xonxoff":
                raise OptionError("flow_control", "software flow control would take the XON "
                                  "and XOFF bytes (0x11, 0x13) out of binary frames",
                                  "use rtscts (wire RTS and CTS) or none")

    options: Options

    def __init__(self, options: Any):
        super().__init__(options)
        self.max_frame = self.options.max_frame
        self.bandwidth = SHARE * line_rate(self.options)
        self._line: Line | None = None
        self._lock = threading.Lock()

    def check_address(self, address: Address) -> Address:
        return (self.options.device, address[1])

    def bind(self, address: Address) -> SerialEndpoint:
        with self._lock:
            if self._line is None or self._line.closed:
                self._line = Line(self.options)  # LinkError when it cannot be opened
            return self._line.bind(address[1])


def line_rate(options: SerialTransport.Options) -> float:
    """Bits per second of frame bytes the line carries: each byte takes a start bit, 8 data
    bits, a parity bit unless ``none``, and the stop bits."""
    bits = 1 + 8 + (options.parity != "none") + options.stop_bits
    return options.baud * 8 / bits


class Line:
    """One open serial port, shared by the endpoints bound on it: one reader thread cuts the
    byte stream into frames and hands each to the endpoint of its destination port."""

    def __init__(self, options: SerialTransport.Options):
        self.options = options
        self.device = options.device
        self.closed = False
        self.endpoints: dict[int, SerialEndpoint] = {}
        self._lock = threading.Lock()
        self._write = threading.Lock()
        self._cut = False  # a write failed part way: the far end holds part of a frame
        self._decoder = serial_datagram.Decoder(self._drop, options.max_frame + PORTS_SIZE)
        try:
            self.port: Any = self._open()
        except OSError as exc:
            raise LinkError(f"cannot open serial port {self.device}: {exc}",
                            "check the device's name (ls /dev/serial/by-id/) and that this "
                            "user may open it (the dialout group)") from None
        self._reader = threading.Thread(target=self._read_loop, daemon=True,
                                        name=f"serial {self.device}")
        self._reader.start()

    def _open(self) -> Any:
        import serial  # behind first use: `rosgate check` loads every plugin

        o = self.options
        return serial.Serial(
            o.device, o.baud, bytesize=serial.EIGHTBITS, parity=o.parity[0].upper(),
            stopbits=o.stop_bits, rtscts=o.flow_control == "rtscts", timeout=POLL,
            write_timeout=1.0, exclusive=True)

    def bind(self, port: int) -> SerialEndpoint:
        with self._lock:
            if port == 0:
                port = next(p for p in range(EPHEMERAL, 65536) if p not in self.endpoints)
            elif port in self.endpoints:
                raise LinkError(f"port {port} of serial port {self.device} is bound already")
            endpoint = self.endpoints[port] = SerialEndpoint(self, port)
            return endpoint

    def release(self, endpoint: SerialEndpoint) -> None:
        with self._lock:
            if self.endpoints.get(endpoint.port) is endpoint:
                del self.endpoints[endpoint.port]
            last = not self.endpoints
        if last:
            self.closed = True
            self._reader.join(timeout=2 * POLL + 1)
            self._close_port()

    def write(self, frame: bytes, source: int, destination: int) -> None:
        if self.options.multiplex:
            frame = destination.to_bytes(2, "big") + source.to_bytes(2, "big") + frame
        data = serial_datagram.encode(frame)
        with self._write:
            port = self.port
            if port is None:
                raise ConnectionError(f"serial port {self.device} is gone")
            if self._cut:  # a frame cut short before: end it, so the next one is whole
                data = bytes((serial_datagram.END,)) + data
            self._cut = True
            port.write(data)  # SerialException and SerialTimeoutException are OSErrors
            self._cut = False

    # -- the reader ---------------------------------------------------------------------------

    def _read_loop(self) -> None:
        while not self.closed:
            port = self.port
            if port is None:
                self._reopen()
                continue
            try:
                data = port.read(max(1, port.in_waiting))
            except (OSError, TypeError, AttributeError):  # TypeError: closed under the read
                if not self.closed:
                    self._gone()
                continue
            if data:
                for frame in self._decoder.feed(data):
                    self._dispatch(frame)

    def _gone(self) -> None:
        log.warning("serial port %s is gone (unplugged?): its link is down until it returns",
                    self.device)
        for endpoint in self._bound():  # first: their links stop sending into it
            endpoint.downs += 1
            endpoint.tell(up=False)
        self._close_port()
        self._decoder = serial_datagram.Decoder(self._drop, self.options.max_frame + PORTS_SIZE)

    def _reopen(self) -> None:
        threading.Event().wait(POLL)
        if self.closed or not os.path.exists(self.device):
            return
        try:
            port = self._open()
        except OSError:
            return  # appearing, or not ours yet: next look
        with self._write:
            self.port = port
        log.info("serial port %s is back (%s): its link is up",
                    self.device, os.path.realpath(self.device))
        for endpoint in self._bound():
            endpoint.tell(up=True)

    def _close_port(self) -> None:
        with self._write:
            port, self.port = self.port, None
        if port is not None:
            try:
                port.close()
            except OSError:
                pass

    def _dispatch(self, frame: bytes) -> None:
        if not self.options.multiplex:
            for endpoint in self._bound():
                if endpoint.port < EPHEMERAL:
                    endpoint.frames.put((frame, (self.device, 0)))
            return
        if len(frame) < PORTS_SIZE:
            self._drop(serial_datagram.TOO_SHORT, f"{len(frame)} bytes, the ports alone take 4")
            return
        destination = int.from_bytes(frame[:2], "big")
        bound = self.endpoints.get(destination)
        if bound is not None:
            source = int.from_bytes(frame[2:PORTS_SIZE], "big")
            bound.frames.put((frame[PORTS_SIZE:], (self.device, source)))

    def _bound(self) -> list[SerialEndpoint]:
        """The endpoints bound now (bind and close run in other threads)."""
        with self._lock:
            return list(self.endpoints.values())

    def _drop(self, reason: Any, detail: str) -> None:
        """A frame the line spoilt: counted by the link of the lowest port that counts."""
        for endpoint in sorted(self._bound(), key=lambda e: e.port):
            if endpoint.drop is not None:
                endpoint.drop(reason, f"serial port {self.device}: {detail}")
                return


class SerialEndpoint:
    """An endpoint at one port of a line."""

    def __init__(self, line: Line, port: int):
        self.line = line
        self.port = port
        self.frames: queue.SimpleQueue[tuple[bytes, Address] | None] = queue.SimpleQueue()
        self.drop: DropCallback | None = None
        self.downs = 0  # times the device vanished while this endpoint was bound
        self._changed: Callable[[bool], None] | None = None
        self._closed = False

    def count_drops(self, drop: DropCallback) -> None:
        """Where frames the line spoilt are counted: ``drop(reason, detail)``."""
        self.drop = drop

    def watch_line(self, changed: Callable[[bool], None]) -> None:
        """Whom to tell that the device is gone (``changed(False)``) or back (True)."""
        self._changed = changed
        if self.line.port is None:
            changed(False)

    def tell(self, up: bool) -> None:
        if self._changed is not None:
            self._changed(up)

    def send(self, frame: bytes, to: Address) -> None:
        self.line.write(frame, self.port, to[1])

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        if self._closed:
            raise OSError("endpoint closed")
        try:
            return self.frames.get(timeout=timeout)  # None: closed
        except queue.Empty:
            return None

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.frames.put(None)  # wakes a receive blocked in another thread
            self.line.release(self)


@hookimpl
def rosgate_transports(register: Any) -> None:
    register(SerialTransport)
