"""The plugin kit: conformance suites and helpers for testing a rosgate plugin.

A distribution of its own (``pip install rosgate-testing``, import ``rosgate_testing``), for a
plugin's tests: a bridge does not need it.

A plugin's test file runs the suite of its kind by subclassing it (the class name must start
with ``Test`` for pytest to collect it)::

    from rosgate_testing import TransportConformance
    from rosgate_transport_unixdgram import UnixDatagramTransport

    class TestUnixDatagramConformance(TransportConformance):
        transport = UnixDatagramTransport      # a Transport subclass, or any factory(options)
        options = {"max_frame": 4096}          # the plugin's table under plugins: (default {})

        @pytest.fixture                        # only for links that do not take 127.0.0.1:port
        def address(self, tmp_path):
            numbers = itertools.count(1)
            return lambda: (str(tmp_path), next(numbers))

    # a bus link (examples/transport_can/tests/test_conformance.py) also overrides far_plugin
    # (the far end as a second instance on the bus) and declares answerable_source = False,
    # ordered = True and, on CAN FD, padded_length

    class TestCborConformance(CodecConformance):
        codec = CborCodec

    class TestNaclConformance(CipherConformance):
        cipher = NaclCipher                    # keys: generate_key() written to a key_file

What each suite checks (every check uses real sockets, real message classes, real keys):

* :class:`TransportConformance` — datagram links: frames of 1 byte up to ``max_frame`` cross
  byte-exact, and the source a receive reports can be answered (or, declared unanswerable, the
  sender's known address); boundaries are kept (and order, where declared); an idle receive
  returns ``None``; ``close`` ends a receive blocked in another thread; frames beyond
  ``max_frame`` cross through the link's own packetizer
  (:class:`rosgate.links.datagram.DatagramLink`: ``fragments``, or ``compact`` pieces below a
  ``max_frame`` of 256).
  Stream links: bytes cross both ways byte-exact (up to 1 MiB, both at once); ``max_bytes``
  is honoured; idle receive and accept return ``None``; when the far end closes, receive
  returns ``b""`` and send raises ``OSError``; ``close`` ends a blocked receive; connecting to
  nobody raises ``OSError``; frames cross whole and in order through
  :class:`rosgate.streamlink.link.StreamLink`, whose ``on_close`` fires when the far end vanishes.
* :class:`CodecConformance` — a round trip of every ROS field kind the installed message
  packages offer (:func:`samples`; raw codecs round-trip the serialized CDR byte for byte), and
  seeded garbage answered by a message of the right type or :class:`rosgate.CodecError`, never
  another exception.
* :class:`CipherConformance` — round trips (empty to 1 MiB) between two instances sharing a
  key; then, for ciphers that authenticate: every flipped bit of the body and of the header,
  another key, every truncation and random bodies are refused with :class:`rosgate.CipherError`;
  two seals of one payload differ. A cipher with ``authenticates = False`` (``none``) skips the
  refusal tests, saying so.
* :class:`BusConformance` — bus links (:mod:`rosgate_fleet.session`): frames of 1 byte to 1 MiB
  cross byte-exact with the concrete key they were published on; ``*`` matches one chunk and ``**``
  any; a reliable publisher keeps order; a closed subscription delivers nothing more; a query is
  answered byte-exact from another thread, one nobody serves is over at once without answers,
  one closed unanswered likewise, one held is over after its timeout; liveliness tokens are
  reported present, arriving and leaving (with their holder too); ``close`` is prompt and leaves
  no thread, and a process that exits without closing does not hang; frames and calls cross
  through :class:`rosgate_fleet.BusLink`, whose full queue is counted.
* :class:`ServiceFramingConformance` — a device's call pattern (:mod:`rosgate.service_framing`):
  a serving port counts and closes every garbage connection without answering, and closes a
  silent one after its idle timeout (see ``service_framings.py``).
* All of them: the plugin is found through its entry point in the group ``rosgate``.

The helpers (:func:`free_port`, :func:`has_ipv6_loopback`, :func:`wait_until_blocked`,
:func:`receive_exactly`, :func:`write_key`, :func:`mutations`, :class:`Frames`) are what plugin
tests kept writing for themselves. This distribution registers this module as a pytest plugin
(entry point ``pytest11``), so pytest rewrites its asserts: a failing check shows the values.
Importing it loads nothing from ROS; the codec suite imports message packages when it runs. One
module per suite: ``transports.py``, ``codecs.py`` (with the sample messages), ``ciphers.py``,
``buses.py``, and ``helpers.py``.
"""

from .buses import BusConformance
from .ciphers import CipherConformance
from .codecs import CodecConformance, sample, samples
from .helpers import (
    Frames,
    free_port,
    has_ipv6_loopback,
    mutations,
    receive_exactly,
    wait_until_blocked,
    write_key,
)
from .packetizers import PacketizerConformance as PacketizerConformance  # each module says
from .service_framings import ServiceFramingConformance as ServiceFramingConformance
from .transforms import TransformConformance as TransformConformance  # what its suite checks
from .transports import TransportConformance

__all__ = [
    "BusConformance", "CipherConformance", "CodecConformance", "Frames", "TransportConformance",
    "free_port", "has_ipv6_loopback", "mutations", "receive_exactly", "sample", "samples",
    "wait_until_blocked", "write_key",
]
