"""What a link does to a packet: its rate (a token bucket), queue, delay, jitter, loss and MTU
(:class:`Profile`), and the model of one direction that the relays drive (:class:`Link`)."""

from __future__ import annotations

import random
import time
from collections import deque
from dataclasses import dataclass

IP_HEADER = 20          # IPv4 header without options
UDP_HEADER = 8
TCP_HEADER = 20         # without options
MAX_UDP_PAYLOAD = 65507  # 65535 - 20 - 8
RTO_MIN = 0.2           # Linux's TCP_RTO_MIN


def ip_fragments(size: int, mtu: int = 1500) -> int:
    """How many IPv4 packets carry a UDP datagram of ``size`` payload bytes over ``mtu``.

    One if ``size + 8 + 20 <= mtu``; else the IP payload (``size + 8``) is cut into fragments
    of ``floor((mtu - 20) / 8) * 8`` bytes (the last one shorter), each with its own header.
    """
    if not 0 <= size <= MAX_UDP_PAYLOAD:
        raise ValueError(f"a UDP datagram over IPv4 holds 0 to {MAX_UDP_PAYLOAD} bytes, not {size}")
    ip_payload = size + UDP_HEADER
    if ip_payload + IP_HEADER <= mtu:
        return 1
    per_fragment = (mtu - IP_HEADER) // 8 * 8
    return -(-ip_payload // per_fragment)


def udp_wire_bytes(size: int, mtu: int = 1500) -> int:
    """Bytes a UDP datagram of ``size`` takes on the link: payload, UDP header, IP headers."""
    return size + UDP_HEADER + IP_HEADER * ip_fragments(size, mtu)


@dataclass(frozen=True)
class Profile:
    """How one direction of an emulated link behaves (both directions get the same profile,
    each with its own state and random streams). Change a copy with
    ``dataclasses.replace(WIFI, loss=0.05)``."""

    rate: float | None = None
    """Link rate in bit/s (a token bucket refilled at this rate); ``None``: unlimited (no
    serialisation time, the queue never fills)."""

    burst: int = 0
    """Size of the token bucket in bytes: that many bytes may leave back to back without
    serialisation time after the link was idle. 0: a plain serialising link."""

    delay: float = 0.0
    """One-way propagation delay in seconds, added to every packet after it left the link."""

    jitter: float = 0.0
    """Extra delay in seconds, drawn per packet uniformly on ``[0, jitter]`` (never negative:
    ``delay`` is the minimum latency, the mean is ``delay + jitter / 2``)."""

    reorder: bool = False
    """UDP only: let jitter reorder datagrams. False (default, as Wi-Fi mostly keeps order): a
    datagram whose draw would overtake the previous one arrives right after it instead.
    TCP always keeps order."""

    loss: float = 0.0
    """Probability that one MTU-sized IP packet is lost (UDP: a datagram is lost when any of
    its fragments is; TCP: the segment is retransmitted after :attr:`rto_s`)."""

    mtu: int = 1500
    """Largest IP packet in bytes. Larger UDP datagrams travel as IPv4 fragments
    (:func:`ip_fragments`); TCP segments carry ``mtu - 40`` bytes."""

    queue: int | None = 1 << 20
    """Bytes (on the wire, headers included) that may wait to be sent onto the link. UDP: a
    datagram that does not fit is dropped (``queue_full``); TCP: the relay stops reading from
    the sender. ``None``: unbounded."""

    rto: float | None = None
    """TCP retransmission timeout in seconds; ``None``: ``max(0.2, 2 * RTT)`` with
    ``RTT = 2 * (delay + jitter)`` (0.2 s is Linux's minimum RTO)."""

    seed: int | str | None = 0
    """Seed of the random streams (loss and jitter, per direction): the same seed and the same
    datagrams give the same UDP losses (TCP's also depend on how reads cut the stream).
    ``None``: fresh randomness from the OS on every relay."""

    def __post_init__(self) -> None:
        if self.rate is not None and not self.rate > 0:
            raise ValueError(f"rate must be > 0 bit/s or None, not {self.rate}")
        if self.burst < 0:
            raise ValueError(f"burst must be >= 0 bytes, not {self.burst}")
        if self.delay < 0 or self.jitter < 0:
            raise ValueError("delay and jitter must be >= 0 seconds")
        if not 0 <= self.loss < 1:
            raise ValueError(f"loss must be in [0, 1), not {self.loss}")
        if self.mtu < 68:
            raise ValueError(f"an IPv4 MTU is at least 68 bytes, not {self.mtu}")
        if self.queue is not None and self.queue <= 0:
            raise ValueError(f"queue must be > 0 bytes or None, not {self.queue}")
        if self.rto is not None and not self.rto > 0:
            raise ValueError(f"rto must be > 0 seconds or None, not {self.rto}")

    @property
    def rto_s(self) -> float:
        """The TCP retransmission timeout in effect (seconds)."""
        if self.rto is not None:
            return self.rto
        return max(RTO_MIN, 2 * 2 * (self.delay + self.jitter))

    @property
    def mss(self) -> int:
        """TCP payload bytes per segment: ``mtu`` minus 20 bytes of IP and 20 of TCP header."""
        return self.mtu - IP_HEADER - TCP_HEADER


WIFI = Profile(rate=20e6, delay=0.010, jitter=0.002, loss=0.01, mtu=1500, queue=250_000)
"""The benchmark's constrained link: 20 Mbit/s, 10 ms one way, 2 ms jitter, 1 % loss, MTU 1500,
a 250 kB queue (100 ms at the rate, about 170 full frames, like a Wi-Fi driver's)."""

PRESETS = {"wifi": WIFI}



def rng(seed: int | str | None, direction: str, purpose: str) -> random.Random:
    if seed is None:
        return random.Random()
    return random.Random(f"rosgate.emulator:{seed}:{direction}:{purpose}")


class Link:
    """The model of one direction: token bucket, queue accounting, loss and jitter draws.

    Not thread-safe: callers hold their relay's lock. Times are ``time.monotonic()``.
    """

    def __init__(self, profile: Profile, direction: str):
        self.profile = profile
        self._loss = rng(profile.seed, direction, "loss")
        self._jitter = rng(profile.seed, direction, "jitter")
        self._tokens = float(profile.burst)
        self._tokens_at = time.monotonic()
        self._free = 0.0                                   # when the last packet left
        self._backlog: deque[tuple[float, int]] = deque()  # (departure, wire bytes), FIFO
        self.queue_bytes = 0
        self.queue_max = 0

    def drain(self, now: float) -> None:
        backlog = self._backlog
        while backlog and backlog[0][0] <= now:
            self.queue_bytes -= backlog.popleft()[1]

    def room(self, now: float) -> int | None:
        """Wire bytes the queue can still take (``None``: unbounded)."""
        self.drain(now)
        return None if self.profile.queue is None else self.profile.queue - self.queue_bytes

    def next_departure(self) -> float | None:
        return self._backlog[0][0] if self._backlog else None

    def lost(self, packets: int) -> bool:
        """Draw the fate of ``packets`` IP packets: True when any one is lost."""
        p = self.profile.loss
        if p <= 0:
            return False
        return sum(self._loss.random() < p for _ in range(packets)) > 0

    def losses(self) -> int:
        """TCP: how many times in a row one segment is lost (0: it arrives the first time)."""
        p, k = self.profile.loss, 0
        while p > 0 and k < 16 and self._loss.random() < p:
            k += 1
        return k

    def send(self, now: float, wire: int) -> float:
        """Put ``wire`` bytes on the link (the caller checked the queue); return when the last
        bit leaves."""
        rate = self.profile.rate
        if rate is None:
            return now
        bytes_per_s = rate / 8
        start = max(now, self._free)
        tokens = min(self.profile.burst,
                     self._tokens + (start - self._tokens_at) * bytes_per_s)
        if tokens >= wire:
            departure, tokens = start, tokens - wire
        else:
            departure, tokens = start + (wire - tokens) / bytes_per_s, 0.0
        self._tokens, self._tokens_at, self._free = tokens, departure, departure
        if departure > now:
            self._backlog.append((departure, wire))
            self.queue_bytes += wire
            self.queue_max = max(self.queue_max, self.queue_bytes)
        return departure

    def arrival(self, departure: float) -> float:
        """When a packet that left at ``departure`` arrives (order not yet enforced)."""
        jitter = self.profile.jitter
        extra = self._jitter.uniform(0.0, jitter) if jitter > 0 else 0.0
        return departure + self.profile.delay + extra
