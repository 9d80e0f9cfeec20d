"""A serial line between two pseudo-terminals: a cable (or a pair of telemetry radios) with a
baud rate, bit errors, lost and doubled bytes, that can be unplugged and plugged back.

:class:`PtyRelay` opens two pseudo-terminal pairs (``os.openpty``) and publishes each slave
end under a stable name (``<folder>/a`` and ``<folder>/b``, symlinks, as ``/dev/serial/by-id``
holds for USB adapters). A program opens ``a`` as its serial port, another ``b``; the relay
copies bytes between the two master ends, one thread per direction, impairing each direction
by its :class:`LineProfile`:

* **baud** — a byte takes ``bits_per_byte / baud`` seconds (start, 8 data bits, parity, stop
  bits: 10 by default); the relay writes no faster, so a sender that outruns the line waits in
  the pseudo-terminal's buffer, as it would in a UART's. A relay thread that wakes late while
  bytes wait catches up, so a busy machine does not make the line slower than its baud rate.
* **flips** — each byte has one bit flipped with probability ``flip`` (``1e-4``: one flipped bit
  per 10,000 bytes); ``drop`` and ``duplicate`` lose or double a byte with their probabilities.
  The seeded random streams make a run repeatable.

:meth:`PtyRelay.unplug` makes both devices vanish (the pseudo-terminals closed, the names
removed); :meth:`PtyRelay.replug` brings them back as new pseudo-terminals — under other
``/dev/pts`` numbers than before — behind the same names. Counters per direction:
``bytes``, ``flipped``, ``dropped``, ``duplicated``. Standard library only.
"""

from __future__ import annotations

import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class LineProfile:
    baud: int = 57_600
    bits_per_byte: float = 10  # start + 8 data + stop
    flip: float = 0.0  # probability a byte has one bit flipped
    drop: float = 0.0  # probability a byte is lost
    duplicate: float = 0.0  # probability a byte is doubled
    seed: int = 0


@dataclass
class LineCounters:
    bytes: int = 0
    flipped: int = 0
    dropped: int = 0
    duplicated: int = 0
    flipped_at: list[int] = field(default_factory=list)  # byte offsets, for tests


class _Pty:
    """One pseudo-terminal pair in raw mode; the slave stays open here too, so the master reads
    no end of file while nobody has the device open."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)  # a write waits in select, where stop is seen
        self.path = os.ttyname(self.slave)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class PtyRelay:
    """Two pseudo-terminals joined by an impaired serial line (see the module's docstring)."""

    def __init__(self, folder: str | os.PathLike[str], up: LineProfile = LineProfile(),
                 down: LineProfile | None = None):
        self.folder = Path(folder)
        self.a = str(self.folder / "a")  # the stable names
        self.b = str(self.folder / "b")
        self.profiles = (up, down if down is not None else up)
        self.counters = (LineCounters(), LineCounters())
        self._rng = [random.Random(f"{p.seed}-{i}") for i, p in enumerate(self.profiles)]
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._ptys: tuple[_Pty, _Pty] | None = None
        self.plugged = threading.Event()
        self.paths: list[str] = []  # every /dev/pts path used, in order
        self._plug(avoid=set())

    @property
    def up(self) -> LineCounters:
        """a -> b"""
        return self.counters[0]

    @property
    def down(self) -> LineCounters:
        """b -> a"""
        return self.counters[1]

    def _plug(self, avoid: set[str]) -> None:
        rejected: list[_Pty] = []
        ptys: list[_Pty] = []
        while len(ptys) < 2:
            pty = _Pty()
            (rejected if pty.path in avoid else ptys).append(pty)
        for pty in rejected:  # held until now so the kernel gave other numbers
            pty.close()
        self._ptys = (ptys[0], ptys[1])
        for name, pty in zip((self.a, self.b), ptys, strict=True):
            tmp = f"{name}.new"
            os.symlink(pty.path, tmp)
            os.replace(tmp, name)
            self.paths.append(pty.path)
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._copy, args=(ptys[0].master, ptys[1].master, 0,
                                                      self._stop), daemon=True),
            threading.Thread(target=self._copy, args=(ptys[1].master, ptys[0].master, 1,
                                                      self._stop), daemon=True)]
        for thread in self._threads:
            thread.start()
        self.plugged.set()

    def unplug(self) -> None:
        """Both devices vanish: names removed, pseudo-terminals closed (the programs that had
        them open read an error)."""
        self.plugged.clear()
        for name in (self.a, self.b):
            try:
                os.unlink(name)
            except FileNotFoundError:
                pass
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2)
        if self._ptys is not None:
            for pty in self._ptys:
                pty.close()
            self._ptys = None

    def replug(self) -> None:
        """Both devices come back as new pseudo-terminals behind the same names."""
        self._plug(avoid=set(self.paths))

    def close(self) -> None:
        self.unplug()

    def __enter__(self) -> PtyRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _copy(self, source: int, target: int, direction: int, stop: threading.Event) -> None:
        profile, counters, rng = self.profiles[direction], self.counters[direction], \
            self._rng[direction]
        byte_time = profile.bits_per_byte / profile.baud
        chunk = max(1, int(0.005 / byte_time))  # about 5 ms of the line per write
        free_at, busy = time.monotonic(), False
        while not stop.is_set():
            try:
                ready, _, _ = select.select([source], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(source, chunk)
            except OSError:
                if stop.wait(0.01):  # closed under us
                    return
                continue
            out = bytearray()
            for byte in data:
                if profile.drop and rng.random() < profile.drop:
                    counters.dropped += 1
                    continue
                if profile.flip and rng.random() < profile.flip:
                    byte ^= 1 << rng.randrange(8)
                    counters.flipped += 1
                    counters.flipped_at.append(counters.bytes + len(out))
                out.append(byte)
                if profile.duplicate and rng.random() < profile.duplicate:
                    out.append(byte)
                    counters.duplicated += 1
            now = time.monotonic()
            if free_at < now - 0.05 and not busy:  # the line was idle: it starts now
                free_at = now
            # else it was busy all along (this thread woke late): the line's time is not lost
            busy = len(data) == chunk  # more was waiting
            free_at += len(out) * byte_time
            wait = free_at - time.monotonic()
            if wait > 0 and stop.wait(wait):
                return
            counters.bytes += len(out)  # before: a reader never holds more than is counted
            if not _write_all(target, bytes(out), stop):
                return


def _write_all(fd: int, data: bytes, stop: threading.Event) -> bool:
    """Write all of ``data`` to a non-blocking ``fd`` as the far end reads it; False when
    stopped (or the pseudo-terminal closed) first."""
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view):]
        except BlockingIOError:
            select.select([], [fd], [], 0.05)
        except OSError:
            return False
        if stop.is_set():
            return False
    return True
