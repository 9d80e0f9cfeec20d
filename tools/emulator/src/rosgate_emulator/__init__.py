"""A user-space emulator of a bad link: rate, delay, jitter, loss, MTU and a bounded queue.

This machine (and many CI machines) has no ``netem``, yet robots live on Wi-Fi and radios.
The relays here sit between two endpoints on real sockets and make the path between them
behave like a constrained link, so a test (or the benchmark's "constrained link" section) can
see what a bridge does when bytes are slow, late and sometimes lost. Standard library only:
nothing here imports rosgate.

What is emulated
----------------

Each direction of a relay is an independent link, described by a :class:`Profile`:

* **Rate** — a token bucket of ``rate`` bit/s holding at most ``burst`` bytes. A packet
  leaves the link (its last bit is sent) at ``max(now, link free) + missing tokens / rate``;
  with ``burst=0`` (the default) that is plain serialisation, ``size * 8 / rate`` after the
  link became free. Sizes count the IP headers (and UDP/TCP headers) of every packet.
* **Queue** — bytes accepted but not yet sent onto the link (``queue``, counted in wire bytes).
  UDP: a datagram that does not fit is tail-dropped (``queue_full``). TCP: the relay stops
  reading from the source socket until the queue has room (backpressure); bytes are never
  dropped.
* **Delay and jitter** — a packet arrives ``delay + U(0, jitter)`` after it left the link:
  jitter is *uniform* on ``[0, jitter]`` and only ever adds, so ``delay`` is the minimum one-way
  latency and the mean is ``delay + jitter / 2``. Order is kept (a packet never overtakes the
  one before it, it waits behind it) unless ``reorder=True`` (UDP only; TCP always keeps order).
* **MTU and IPv4 fragments** — a UDP datagram of ``n`` bytes travels as
  :func:`ip_fragments` ``(n, mtu)`` IPv4 packets: one if ``n + 28 <= mtu``, else
  ``ceil((n + 8) / (8 * floor((mtu - 20) / 8)))`` fragments (each fragment has its own 20-byte IP
  header, the 8-byte UDP header rides in the first, fragment payloads are multiples of 8).
  E.g. at MTU 1500: 1,472 bytes is 1 packet, 1,473 is 2, 4,000 is 3 (1480 + 1480 + 1048).
  Wire bytes: :func:`udp_wire_bytes` ``= n + 8 + 20 * fragments``.
* **Loss** — each IP packet is lost with probability ``loss``, independently. A UDP datagram
  is lost when any one of its fragments is (so a 3-fragment datagram at 10 % is lost with
  probability 1 - 0.9**3 = 27.1 %). A lost datagram still took its time on the link.
  TCP (segments of ``mss = mtu - 40`` bytes, 40 wire bytes of headers each) never loses bytes:
  a lost segment is retransmitted after the retransmission timeout (:attr:`Profile.rto_s`,
  by default ``max(200 ms, 2 * RTT)`` with ``RTT = 2 * (delay + jitter)``: 200 ms is Linux's
  minimum RTO), doubling for each further loss of the same segment, and everything behind it
  waits (head-of-line blocking). Each retransmitted copy takes link time too.
* **Seeds** — ``seed`` makes every run the same: each direction has its own random streams,
  one for loss and one for jitter, derived from the seed and the direction's name. The UDP
  loss draw is made for every datagram in arrival order (before the queue check), so the same
  seed and the same datagrams give the same loss pattern whatever the timing.

What is not emulated
--------------------

The shaping relays never duplicate, corrupt or truncate (the fault relays of :mod:`.faults`
do, on demand: see below); no bursty (Gilbert-Elliott) loss, no varying rate, no link-layer
retransmission. TCP is modelled optimistically: the relay's sender never slows down after
a loss (no congestion window, no slow start, no fast retransmit or SACK), so it shows
head-of-line blocking and the cost of retransmissions but not the throughput collapse of real
TCP under heavy loss; treat its throughput as an upper bound. The relay's own sockets are
real: TCP connection set-up and the relay's kernel buffers (4 MiB) add nothing modelled. The
fragment arithmetic is IPv4's even when the relay listens on IPv6. :class:`UdpRelay` answers
one client at a time (the last one that sent), as a NAT with one mapping would.

Use from a test
---------------

::

    from rosgate_emulator import WIFI, Profile, UdpRelay, TcpRelay

    def test_my_link_on_wifi(bridge_b_port):
        lossy = Profile(rate=2e6, delay=0.01, jitter=0.002, loss=0.1, seed=7)
        with UdpRelay(lossy, target=("127.0.0.1", bridge_b_port)) as link:
            ...                                   # point side A at link.address
            assert link.wait_until(lambda up, down: up.datagrams_delivered >= 100, timeout=5)
            assert link.up.dropped["loss"] > 0

The relay answers the address it last heard from, so a bridge that replies to the source it
saw works through it. ``close()`` (or leaving the ``with``) stops its threads and closes its
sockets at once; datagrams still in flight are discarded. :meth:`UdpRelay.wait_until` and
:meth:`TcpRelay.wait_until` wait on the counters without polling. A delivery is counted just
before it is handed to the socket, so a receiver never holds more than the counters say.

Timing is faithful while the machine keeps up: a UDP datagram's time on the emulated link
starts when the kernel stamped its arrival at the relay (so a relay thread that runs late does
not add delay), and ``late_max`` in the counters says how much later than due the relay
handed anything over. If that is not small beside ``jitter``, a busy machine, not the
profile, shaped the latencies.

Use from the benchmark
----------------------

Put a relay between the two bridges, one per port the far bridge listens on (a
:class:`TcpRelay` for the main line, a :class:`UdpRelay` per UDP port), with the :data:`WIFI`
preset (20 Mbit/s, 10 ms, 2 ms jitter, 1 % loss, MTU 1500)::

    with UdpRelay(WIFI, target=("127.0.0.1", port_b)) as link:
        ...   # bridge A's peer / server address = link.address

To keep the relay's threads away from the measured processes' GIL, run it as a process of
its own; it prints its address, runs until SIGINT/SIGTERM, then prints its counters as JSON::

    python -m rosgate_emulator udp --target 127.0.0.1:13001 --listen 127.0.0.1:12001 \\
        --preset wifi [--rate 1e7] [--loss 0.05] [--seed 3]

Real kernel links: :class:`NetnsPair` (root only) makes two network namespaces joined by a
veth pair, optionally capped by the kernel's ``tbf`` qdisc, for tests that need two hosts
with their own IP stacks; put a relay inside for delay, jitter and loss (``netem`` is not
available here).

Faults on demand
----------------

Where the shaping relays make a link statistically bad, :class:`FaultProxy` (TCP and UDP on
one port, as a client's ``server:`` address is), :class:`TcpFaults` and :class:`UdpFaults`
(:mod:`.faults`) break it the way a test asks: cut, stall, slow, refuse or mangle TCP
connections; drop, duplicate, reorder, delay, corrupt or truncate datagrams at the rates of
:class:`UdpRates`, from a seeded random stream, and rebind (a NAT that lost its mapping).

Modules: :mod:`.shaping` (profiles and the link model), :mod:`.relay` (what both relays share),
:mod:`.udp` and :mod:`.tcp` (the relays), :mod:`.faults`, :mod:`.netns`, :mod:`.serial` (a
serial line between two pseudo-terminals) and :mod:`.cli` (``python -m rosgate_emulator``).
"""

from .faults import FaultProxy, TcpFaults, UdpFaults, UdpRates
from .netns import NetnsPair
from .shaping import (
    IP_HEADER,
    MAX_UDP_PAYLOAD,
    PRESETS,
    TCP_HEADER,
    UDP_HEADER,
    WIFI,
    Profile,
    ip_fragments,
    udp_wire_bytes,
)
from .tcp import TcpCounters, TcpRelay
from .udp import UdpCounters, UdpRelay

__all__ = [
    "FaultProxy", "IP_HEADER", "MAX_UDP_PAYLOAD", "NetnsPair", "PRESETS", "Profile", "TCP_HEADER",
    "TcpCounters", "TcpFaults", "TcpRelay", "UDP_HEADER", "UdpCounters", "UdpFaults", "UdpRates",
    "UdpRelay", "WIFI", "ip_fragments", "udp_wire_bytes",
]
