"""Which cipher seals and opens a route's frames: :class:`StaticKeys`, one cipher from the file's
options (peer role, ``insecure: true``), or a session's keys (:mod:`rosgate.secure`), which
change with every key generation and handshake.

A static key never changes, so a frame sealed under it stays valid forever: a peer keyed by a
file keeps a :class:`ReplayRecord` so that frames captured before it restarted are refused after.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path

from .cipher import Cipher

log = logging.getLogger("rosgate")


class NoKey(LookupError):
    """There is no key to seal under yet (a session whose handshake has not happened)."""


class Changes:
    """What a route reads, without a call, to know the ciphers it holds are still its keys':
    :attr:`version` changes whenever they may have changed otherwise than with time."""

    version = 0


#: the changes of keys that never change
NEVER = Changes()


class Keys(ABC):
    """The ciphers of one route, by the envelope's epoch."""

    #: True when ``open`` proves a frame came from a key holder unchanged
    authenticates: bool = True
    #: True when a frame's send time is these keys' to give (:meth:`stamp`) and to judge
    #: (:meth:`fresh`); False (a session's keys): the send time is the clock's, and any frame
    #: the keys open is of this run. A route calls neither per frame unless it is True.
    dated: bool = False
    #: True when every epoch's cipher is the none cipher: a frame's body is its payload
    plain: bool = False
    #: see :meth:`sealing`: a route holds a cipher while ``changes.version`` stays and
    #: ``clock()`` has not reached the time it was given with it
    changes: Changes = NEVER
    clock: Callable[[], float] = staticmethod(time.monotonic)

    @abstractmethod
    def epoch(self) -> int:
        """The epoch a frame sealed now carries; :class:`NoKey` when there is none yet."""

    @abstractmethod
    def sealer(self, epoch: int) -> Cipher:
        """The cipher that seals frames of ``epoch`` (a reply seals under its request's)."""

    @abstractmethod
    def opener(self, epoch: int) -> Cipher | None:
        """The cipher that opens frames of ``epoch``; None when no key of this route has it
        (an earlier session, a server restart, a generation long expired)."""

    def sealing(self) -> tuple[int, Cipher, float]:
        """The epoch a frame sealed now carries, its cipher, and until when (by :attr:`clock`)
        a route may seal under both without asking again; :class:`NoKey` when there is none."""
        epoch = self.epoch()
        return epoch, self.sealer(epoch), float("inf")

    def opening(self, epoch: int) -> tuple[Cipher, float] | None:
        """The cipher that opens frames of ``epoch`` and until when a route may keep it; None
        as :meth:`opener`."""
        cipher = self.opener(epoch)
        return None if cipher is None else (cipher, float("inf"))

    def stamp(self, now: int) -> int:
        """The send time a frame sealed now carries in its envelope (``now``: time.time_ns())."""
        return now

    def fresh(self, epoch: int, stamp: int) -> bool:
        """Whether an opened frame of ``epoch`` sent at ``stamp`` may be new (the replay window
        then judges its sequence number); False: perhaps taken already. A session's keys end
        with their session, so any frame they open is of this run."""
        return True


class StaticKeys(Keys):
    """One cipher for every epoch; the epoch only starts a new sequence at each sender start.

    With a ``record`` (:class:`ReplayRecord`), send times grow across the sender's starts, and
    a frame sent before this side's start is refused; so is one of a sender start the replay
    window forgot (it keeps the last ``EPOCHS``), by the latest send time seen in it: sound with
    one sender, whose later starts stamp later."""

    EPOCHS = 8  # as the replay window's

    def __init__(self, cipher: Cipher, record: ReplayRecord | None = None):
        self.cipher = cipher
        self.authenticates = cipher.authenticates
        self._epoch = int.from_bytes(os.urandom(4), "big")
        self.record = record
        self.dated = record is not None
        self.plain = cipher.plain
        self._floor = -1  # frames sent at or before this are of a forgotten epoch
        self._latest: dict[int, int] = {}  # epoch -> the latest send time taken in it
        if record is not None:
            self.stamp = record.stamp  # type: ignore[method-assign]

    def fresh(self, epoch: int, stamp: int) -> bool:
        if self.record is None:
            return True
        if stamp <= self._floor or not self.record.fresh(stamp):
            return False
        latest = self._latest.get(epoch)
        if latest is None:
            if len(self._latest) >= self.EPOCHS:
                self._floor = max(self._floor, self._latest.pop(next(iter(self._latest))))
                if stamp <= self._floor:
                    return False
            self._latest[epoch] = stamp
        elif stamp > latest:
            self._latest[epoch] = stamp
        return True

    def epoch(self) -> int:
        return self._epoch

    def sealer(self, epoch: int) -> Cipher:
        return self.cipher

    def opener(self, epoch: int) -> Cipher | None:
        return self.cipher


class ReplayRecord:
    """What a bridge keyed by a file remembers across its restarts, in one small file of its
    state folder (:func:`rosgate.runtime.state_dir`): how late a send time it has put on its
    frames (``sent``) and taken from its peer's (``heard``), both by the sender's clock.

    A frame whose (authenticated) send time is not after what the record said at start was sent
    before this start, perhaps taken already: refused. Every frame sent is stamped after
    anything sent before this start, so a restarted sender is never taken for a replayer, even
    when its clock went back. Each mark is written *before* a frame goes past it, ``AHEAD`` s of
    send time at a time, so the file changes about once a second while frames flow, never per
    frame; a restart within ``AHEAD`` of the last frame refuses up to ``AHEAD`` of the peer's
    frames that follow. A record that is lost (or a first start) refuses nothing: :attr:`known`
    is False, and the bridge says so at start.
    """

    AHEAD = 1_000_000_000  # ns

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()
        # one bridge per record: two writing one file would each lose the other's marks
        self._holder = open(os.open(path.with_name(path.name + ".lock"),  # held until close
                                    os.O_RDWR | os.O_CREAT, 0o600), "rb")
        try:
            fcntl.flock(self._holder, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._holder.close()
            raise OSError(f"another bridge keeps its replay record in {path}") from None
        try:
            data = json.loads(path.read_text())
            sent, heard = int(data["sent"]), int(data["heard"])
        except FileNotFoundError:
            self.known, self.unreadable = False, ""
            sent = heard = 0
        except (OSError, ValueError, TypeError, KeyError) as exc:  # refused as missing: said
            self.known, self.unreadable = False, f"{type(exc).__name__}: {exc}"
            sent = heard = 0
        else:
            self.known, self.unreadable = True, ""
        #: frames sent at or before this were (or may have been) taken before this start
        self.floor = heard
        #: every frame stamped after the last start is stamped after this
        self.first = sent + self.AHEAD + 1 if self.known else 0
        self._sent, self._heard = sent, heard  # the marks as the file has them
        self._failing = False  # the last write failed (said once until one succeeds)

    def stamp(self, now: int) -> int:
        stamp = now if now >= self.first else self.first
        if stamp > self._sent:
            self._mark(sent=stamp)
        return stamp

    def fresh(self, stamp: int) -> bool:
        if stamp <= self.floor:
            return False
        if stamp > self._heard:
            self._mark(heard=stamp)
        return True

    def close(self) -> None:
        """The bridge stops: the record is free for its next start. (The marks stay ``AHEAD``:
        writing the exact latest times would take a lock on every frame, 0.3 µs each here.)"""
        self._holder.close()

    def _mark(self, sent: int = 0, heard: int = 0) -> None:
        """The file says ``AHEAD`` past ``sent`` or ``heard`` (before the frame goes on)."""
        with self._lock:
            if sent > self._sent:
                marks = sent + self.AHEAD, self._heard
            elif heard > self._heard:
                marks = self._sent, heard + self.AHEAD
            else:
                return  # another thread has marked it
            try:
                self._write(json.dumps({"sent": marks[0], "heard": marks[1]}).encode())
            except OSError as exc:  # the frame goes on: a robot is not stopped by a full disk
                if not self._failing:
                    log.error("cannot write %s (%s): frames taken now could be replayed after "
                              "a restart", self.path, exc.strerror or exc)
                self._failing = True
            else:
                self._failing = False
            # only now: another thread's frame below the new marks may go on without waiting
            self._sent, self._heard = marks

    def _write(self, text: bytes) -> None:
        """The file replaced whole (a crash leaves the old one or the new one)."""
        partial = self.path.with_name(self.path.name + ".new")
        fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, text)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(partial, self.path)
