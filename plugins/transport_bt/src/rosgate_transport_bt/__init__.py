"""rosgate transport ``bt``: Bluetooth RFCOMM byte streams.

A stream link, like tcp: the rosgate core frames, reconnects and counts; this plugin only opens
RFCOMM sockets (``AF_BLUETOOTH``, ``SOCK_STREAM``, ``BTPROTO_RFCOMM``). Usable for the main line
(``main_line: bt``) and for topics (``transport: bt``).

Addresses: ``AA:BB:CC:DD:EE:FF/5`` — the device address, a slash, the RFCOMM channel (1-30).
The slash keeps it from being read as ``host:port``. A server listens on its own adapter's
address (or ``00:00:00:00:00:00``, any adapter); a client connects to the server's. For a topic
with ``port:``, the port is the channel and the host is the server's (or peer's) device address.

Pairing and trust are the operating system's job (``bluetoothctl``); this plugin neither pairs
nor advertises an SDP record, so both sides must agree on the channel.

Options (``plugins: {bt: {...}}``): ``emulate_dir``, for tests on machines without a radio:
each "RFCOMM" stream is carried over an AF_UNIX stream socket named
``<dir>/AA_BB_CC_DD_EE_FF-<channel>`` instead. Everything above the socket (addresses, listen,
accept, connect, framing, reconnection) is the same code. Not for robots.
"""

from __future__ import annotations

import os
import re
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosgate import (
    Address,
    LinkError,
    OptionError,
    SocketConnection,
    SocketListener,
    StreamTransport,
    hookimpl,
    option,
)

CHANNELS = range(1, 31)
ANY = "00:00:00:00:00:00"
_BDADDR = re.compile(r"[0-9A-F]{2}(?::[0-9A-F]{2}){5}")
_NOTATION = "a device address and an RFCOMM channel, for example AA:BB:CC:DD:EE:FF/5"
NO_BLUETOOTH = ("this Python was built without Bluetooth support (socket.AF_BLUETOOTH); use a "
                "Python built with the BlueZ headers (libbluetooth-dev) installed, such as the "
                "system's python3 on Linux")
NO_BLUETOOTH_FIX = ("on Debian/Ubuntu: apt install libbluetooth-dev, then rebuild Python (or use "
                    "/usr/bin/python3); or pick another transport")


def rfcomm_socket() -> socket.socket:
    """A fresh RFCOMM stream socket; LinkError when this Python cannot make one."""
    family = getattr(socket, "AF_BLUETOOTH", None)
    if family is None:
        raise LinkError(NO_BLUETOOTH)
    try:
        return socket.socket(family, socket.SOCK_STREAM, socket.BTPROTO_RFCOMM)
    except OSError as exc:
        raise LinkError(f"cannot open an RFCOMM socket: {exc.strerror} (is there a Bluetooth "
                        "adapter, and is bluetoothd running?)") from None


class BluetoothTransport(StreamTransport):
    name = "bt"

    @dataclass(frozen=True)
    class Options:
        emulate_dir: str | None = option(
            None, "tests only: a directory where AF_UNIX sockets stand in for RFCOMM")

        def __post_init__(self) -> None:
            if self.emulate_dir == "":
                raise OptionError("emulate_dir", "must be a directory path, not ''")
            if self.emulate_dir is None and not hasattr(socket, "AF_BLUETOOTH"):
                raise OptionError(None, NO_BLUETOOTH, NO_BLUETOOTH_FIX)

    options: Options

    def __init__(self, options: Options):
        super().__init__(options)
        self.emulate_dir = Path(self.options.emulate_dir) if self.options.emulate_dir else None

    # -- addresses -------------------------------------------------------------------------
    def parse_address(self, text: str) -> Address:
        device, slash, channel = text.strip().partition("/")
        if not slash or not channel.isdigit():
            raise ValueError(f"{text!r} is not {_NOTATION}")
        return self.check_address((device, int(channel)))

    def check_address(self, address: Address) -> Address:
        device, channel = address
        if not _BDADDR.fullmatch(device.upper()):
            raise ValueError(f"{device!r} is not a Bluetooth device address: expected {_NOTATION}")
        if channel not in CHANNELS:
            raise ValueError(f"RFCOMM channel {channel} is out of range: channels are 1 to 30 "
                             f"(address {device}/{channel})")
        return device.upper(), channel

    # -- streams ---------------------------------------------------------------------------
    def listen(self, address: Address) -> SocketListener:
        if self.emulate_dir is not None:
            return self._listen_emulated(address)
        sock = rfcomm_socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
            sock.listen(8)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot listen on RFCOMM {address[0]}/{address[1]}: "
                            f"{exc.strerror}") from None
        return SocketListener(sock)

    def connect(self, address: Address, timeout: float) -> SocketConnection:
        if self.emulate_dir is not None:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            target: Any = str(self._path(address))
        else:
            sock, target = rfcomm_socket(), address
        sock.settimeout(timeout)
        try:
            sock.connect(target)
        except OSError:
            sock.close()
            raise
        return SocketConnection(sock)

    # -- the test stand-in -----------------------------------------------------------------
    def _path(self, address: Address) -> Path:
        assert self.emulate_dir is not None
        return self.emulate_dir / f"{address[0].upper().replace(':', '_')}-{address[1]}"

    def _listen_emulated(self, address: Address) -> SocketListener:
        path = self._path(address)
        _remove_if_stale(path)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(path))
            sock.listen(8)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot listen on RFCOMM {address[0]}/{address[1]} (emulated at "
                            f"{path}): {exc.strerror}") from None
        return SocketListener(sock, address_of=lambda _unnamed: (ANY, 0))  # who: unknown


def _remove_if_stale(path: Path) -> None:
    """A socket file left by a listener that died is removed; a live one is left (bind then
    fails with 'in use', as a busy RFCOMM channel would)."""
    if not path.exists():
        return
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(str(path))
    except ConnectionRefusedError:
        os.unlink(path)
    except OSError:
        pass
    finally:
        probe.close()


@hookimpl
def rosgate_transports(register):
    register(BluetoothTransport)
