"""What the sending side of an entry says about it before a frame is published: its type with
ROS's RIHS01 hash, and the QoS it found (when the entry sets none). Said in the hello and the
welcome, and announced on the entry's link at once and every :data:`ANNOUNCE_EVERY` seconds as
``{"type": ..., "hash": ..., "qos": {...}}`` under ``FLAG_ANNOUNCE``, sealed like its data.
The serving side of a client/server service says too whether a real ROS server of it runs there
(``"served"``): the calling side's proxy exists only while one does.
A receiving side whose type differs refuses the entry (``type_mismatch``, or
``type_not_installed`` naming the package when the far side's type is not installed here); one
waiting for the far side's first word holds what comes (:meth:`TypeCheck.expect`).
docs/configuration.md says the rest."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .config import QOS_POLICIES
from .drops import Drop, Reason
from .rostypes import TypeNotFound, resolve_type
from .warn import Warner
from .wire.control import parse

log = logging.getLogger("rosgate")

ANNOUNCE_EVERY = 2.0  # seconds between two announcements of one entry (after its first ones)
ANNOUNCE_FAST = 0.5  # seconds between them while the entry is young:
YOUNG = 2.0  # seconds after its start
MISMATCH_EVERY = 60.0  # seconds between two sentences about one entry's mismatch
MAX_DEPTH = 1000  # of an announced QoS: what a far side may make this side keep
#: seconds a receiving entry holds frames for its far side's first announcement (two periods:
#: one announcement may be lost on the way)
HOLD_FOR = 2 * ANNOUNCE_EVERY
HOLD_FRAMES = 1000  # frames held meanwhile, at most
HOLD_BYTES = 16 << 20  # and bytes

#: one sentence per entry and minute, whoever's frames it drops
MISMATCHES = Warner(MISMATCH_EVERY)


@dataclass(frozen=True)
class Identity:
    """A type as one side knows it: its name and its RIHS01 hash (None: unknown)."""

    name: str
    hash: str | None

    def __str__(self) -> str:
        return f"{self.name} ({self.hash or 'no hash'})"


def item(identity: Identity, qos: dict[str, Any] | None,
         served: bool | None = None) -> dict[str, Any]:
    """One entry's item of a hello or a welcome, and its announcement's body (``served``:
    whether a real ROS server of the service runs on this side; None: not said)."""
    body: dict[str, Any] = {"type": identity.name}
    if identity.hash is not None:
        body["hash"] = identity.hash
    if qos is not None:
        body["qos"] = dict(qos)
    if served is not None:
        body["served"] = served
    return body


def encode(body: dict[str, Any]) -> bytes:
    return json.dumps(body, separators=(",", ":")).encode()


def read(item: Any) -> tuple[Identity | None, dict[str, Any] | None]:
    """An announcement's or a hello item's type and QoS; (None, None) from an older peer;
    ValueError when unreadable."""
    if item is None:
        return None, None
    if not isinstance(item, dict):
        raise ValueError("an entry's announcement is not a mapping")
    name, found = item.get("type"), item.get("hash")
    if not isinstance(name, str) or not (found is None or isinstance(found, str)):
        raise ValueError("an announcement's type or hash is not a string")
    return Identity(name[:200], None if found is None else found[:100]), qos_of(item.get("qos"))


def parse_body(body: bytes) -> tuple[Identity | None, dict[str, Any] | None]:
    """An announcement frame's (opened) body; ValueError when it is not one."""
    return read(parse(body))  # a ControlError is a ValueError


def served(said: Any) -> bool:
    """Whether the far side says a real server of the service runs there: an announcement's
    body (bytes) or a hello's or a welcome's item; a far side that says nothing of it (an older
    rosgate) is taken at its word that one does, as before. ValueError when unreadable."""
    body = parse(said) if isinstance(said, bytes) else said
    value = body.get("served", True) if isinstance(body, dict) else True
    if not isinstance(value, bool):
        raise ValueError(f"an announcement's served is {value!r}, not true or false")
    return value


def qos_of(value: Any) -> dict[str, Any] | None:
    """An announced QoS (from the network), checked."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise ValueError("an announced QoS is not a mapping")
    qos: dict[str, Any] = {}
    for policy in ("reliability", "durability"):
        if value.get(policy) not in QOS_POLICIES[policy]:
            raise ValueError(f"announced {policy} {value.get(policy)!r} is none of "
                             f"{', '.join(QOS_POLICIES[policy])}")
        qos[policy] = value[policy]
    depth = value.get("depth")
    if not isinstance(depth, int) or isinstance(depth, bool) or not 1 <= depth <= MAX_DEPTH:
        raise ValueError(f"announced depth {depth!r} is not 1..{MAX_DEPTH}")
    qos["depth"] = depth
    return qos


#: a held frame, delivered (True: the types agree) or refused (False) once the far side speaks
Verdict = Callable[[bool], None]


class TypeCheck:
    """One entry's type against what the far side says of its own."""

    __slots__ = ("label", "mine", "theirs", "mismatch", "reason", "heard_at", "awaiting", "pace",
                 "_said", "_held", "_held_bytes", "_since", "_drop", "_lock")

    def __init__(self, label: str, mine: Identity):
        self.label = label
        self.mine = mine
        self.theirs: Identity | None = None
        self.mismatch: str | None = None  # why the entry is refused; None while types agree
        #: how its refused frames are counted: another type, or one not installed here
        self.reason: Drop = Drop.TYPE_MISMATCH
        self.heard_at: float | None = None  # when the far side last said its type (monotonic)
        self.awaiting = False  # frames wait for the far side's first word (:meth:`expect`)
        self._said: set[str] = set()
        self._held: deque[tuple[int, Verdict]] = deque()
        self._held_bytes = 0
        self._since = 0.0
        self._drop: Callable[[Reason, str], None] = lambda reason, detail: None
        #: told how many held frames went on so far, as they go: a publisher paces its release
        self.pace: Callable[[int], None] = lambda went: None
        self._lock = threading.RLock()

    def expect(self, drop: Callable[[Reason, str], None]) -> None:
        """Hold frames until the far side says its type; ``drop`` counts a frame let go."""
        self._drop = drop
        self.awaiting = True

    def hold(self, size: int, verdict: Verdict) -> bool:
        """True: the frame is held until the far side's first word gives its ``verdict``;
        False: it goes on now."""
        with self._lock:
            if not self.awaiting:
                return False
            now = time.monotonic()
            if not self._held:
                self._since = now
            self._held.append((size, verdict))
            self._held_bytes += size
            while len(self._held) > HOLD_FRAMES or self._held_bytes > HOLD_BYTES:
                gone, _ = self._held.popleft()
                self._held_bytes -= gone
                self._drop(Drop.TYPE_UNHEARD, f"more than {HOLD_FRAMES} frames or "
                           f"{HOLD_BYTES >> 20} MiB came before the far side said its type")
            self.expire(now)
            return True

    def expire(self, now: float) -> None:
        """A far side silent :data:`HOLD_FOR` seconds after the first held frame is an older
        rosgate, which never announces: what was held goes on, unchecked."""
        with self._lock:
            if self.awaiting and self._held and now - self._since > HOLD_FOR:
                self._once("silent", f"{self.label}: the far side said nothing of its type in "
                                     f"{HOLD_FOR:g} s (an older rosgate?): its type is not "
                                     "checked until it does")
                self._settle()

    def far(self, theirs: Identity | None) -> None:
        """What the far side says of its type (None: nothing, an older rosgate)."""
        with self._lock:
            self.heard_at = time.monotonic()
            self._judge(theirs)
            self._settle()

    def _judge(self, theirs: Identity | None) -> None:
        if theirs is None or theirs.hash is None or self.mine.hash is None:
            self.mismatch = None
            who = "the far side" if theirs is None or theirs.hash is None else "this side"
            self._once(who, f"{self.label}: {who} gives no type hash (an older rosgate, or a "
                            f"ROS before Iron): its type is not checked")
            return
        if theirs.hash == self.mine.hash:
            self.theirs, self.mismatch = theirs, None
            return
        if self.mismatch is None or theirs != self.theirs:  # judged once per type it says
            self.reason, self.mismatch = Drop.TYPE_MISMATCH, (
                f"{self.label}: refused, the far side's type is {theirs} and this side's is "
                f"{self.mine}, so its frames are dropped")
            missing = not_installed(theirs.name) if theirs.name != self.mine.name else None
            if missing is not None:
                self.reason, self.mismatch = Drop.TYPE_NOT_INSTALLED, (
                    f"{self.label}: refused, the far side's type {theirs.name} is not installed "
                    f"on this side: {missing}, so its frames are dropped")
        self.theirs = theirs
        self.say()

    def _settle(self) -> None:
        """What was held is published, or refused, in the order it came."""
        self.awaiting = False
        held, self._held, self._held_bytes = self._held, deque(), 0
        agreed = self.mismatch is None
        for went, (_, verdict) in enumerate(held, 1):
            verdict(agreed)
            if agreed:
                self.pace(went)

    def say(self) -> None:
        """Say the mismatch, at most once per :data:`MISMATCH_EVERY` seconds."""
        held = MISMATCHES.due(self.label, self.reason.value)
        if held is not None and self.mismatch is not None:
            log.error("%s%s", self.mismatch, f" ({held} more since)" if held else "")

    def _once(self, key: str, sentence: str) -> None:
        if key not in self._said:
            self._said.add(key)
            log.warning("%s", sentence)


def not_installed(type_name: str) -> str | None:
    """Why a type the far side names cannot be loaded here (the package to install, by the
    type's name); None when it is installed."""
    try:
        resolve_type(type_name)
    except TypeNotFound as exc:
        return str(exc)
    return None
