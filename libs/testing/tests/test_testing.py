"""The plugin kit itself: its samples cover the field kinds they claim, and its suites fail for
a plugin that breaks the contract (a suite that cannot fail proves nothing)."""

from __future__ import annotations

import importlib
import subprocess
import sys
import textwrap

from rosgate_message_tree import type_name
from rosgate_testing import samples
from rosidl_parser import definition as idl


def kinds(t: idl.AbstractType, found: set[str]) -> set[str]:
    """Every field kind under a rosidl type, nested messages included, in rosidl's spelling."""
    if isinstance(t, idl.NamespacedType):
        if type_name(t) not in found:
            found |= {"message", type_name(t)}
            cls = getattr(importlib.import_module(".".join(t.namespaces)), t.name)
            for slot in cls.SLOT_TYPES:
                kinds(slot, found)
        return found
    found.add(type_name(t))
    if isinstance(t, idl.AbstractNestedType):
        kinds(t.value_type, found)
    return found


def test_samples_cover_every_field_kind_they_claim():
    covered: set[str] = set()
    for make in samples().values():
        message = type(make())
        kinds(idl.NamespacedType(message.__module__.split(".")[:2], message.__name__), covered)
    claimed = {"int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float",
               "double", "boolean", "octet", "string", "string<256>", "double[36]", "double[9]",
               "uint8[16]", "sequence<uint8>", "sequence<octet>", "sequence<double>",
               "sequence<float>", "sequence<int8>", "sequence<uint16>", "sequence<int32>",
               "sequence<int64>", "sequence<uint64>", "sequence<boolean>", "sequence<string>",
               "sequence<rcl_interfaces/FloatingPointRange, 1>", "message"}
    assert claimed <= covered, sorted(claimed - covered)
    assert not any(k.startswith("wstring") for k in covered)  # the docstring says: not covered


def test_the_suites_fail_for_broken_plugins(tmp_path):
    """Plugins that each break one rule, or declare what they do not do, run through the
    suites in a pytest of their own."""
    (tmp_path / "test_broken.py").write_text(textwrap.dedent('''
        from rosgate import Cipher
        from rosgate.builtin import CdrCodec
        from rosgate_testing import CipherConformance, CodecConformance, TransportConformance
        from rosgate_transport_udp import UdpTransport

        class LeakyCodec(CdrCodec):        # lets garbage through as another exception
            def decode(self, data):
                return data[:4].decode() and super().decode(data)

        class MalleableCipher(Cipher):     # "authenticates", but checks nothing
            name = "malleable"
            def seal(self, header, payload):
                return payload
            def open(self, header, body):
                return body

        class SmallUdp(UdpTransport):      # claims more than it can carry
            def __init__(self, options):
                super().__init__(options)
                self.max_frame = 70_000    # (udp's max_frame option stops at 65,000)

        class SwappingUdp(UdpTransport):   # hands over datagrams two by two, swapped
            def bind(self, address):
                endpoint = super().bind(address)
                receive, held = endpoint.receive, []
                def swapped(timeout):
                    if held:
                        return held.pop()
                    first = receive(timeout)
                    second = receive(1.0) if first else None
                    if second is None:
                        return first
                    held.append(first)
                    return second
                endpoint.receive = swapped
                return endpoint

        class TestLeaky(CodecConformance):
            codec = LeakyCodec

        class TestMalleable(CipherConformance):
            cipher = MalleableCipher

        class TestSmallUdp(TransportConformance):
            transport = SmallUdp

        class TestSwappingUdp(TransportConformance):
            transport = SwappingUdp
            ordered = True                 # declares an order it does not keep

        class TestPaddedUdp(TransportConformance):
            transport = UdpTransport
            padded_length = staticmethod(lambda n: n + 1)  # declares padding UDP never adds
    '''))
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "-p", "no:warnings", str(tmp_path / "test_broken.py")],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    failed = {line.split("::", 1)[1].split(" ")[0] for line in done.stdout.splitlines()
              if line.startswith("FAILED")}
    for expected in ["TestLeaky::test_garbage_is_a_codec_error_and_nothing_else",
                     "TestLeaky::test_found_through_its_entry_point",
                     "TestMalleable::test_every_flipped_bit_of_the_body_is_refused",
                     "TestMalleable::test_every_flipped_bit_of_the_header_is_refused",
                     "TestMalleable::test_another_key_is_refused",
                     "TestMalleable::test_two_seals_of_one_payload_differ",
                     "TestSmallUdp::test_datagram_crosses_byte_exact_and_can_be_answered[max_frame]",
                     "TestSwappingUdp::test_datagram_boundaries_are_kept",
                     "TestPaddedUdp::test_datagram_crosses_byte_exact_and_can_be_answered[max_frame-1]",
                     "TestPaddedUdp::test_datagram_boundaries_are_kept"]:
        assert expected in failed, done.stdout[-3000:]
    assert "TestLeaky::test_round_trip[Twist]" not in failed  # what works still passes
    # unordered, a swapping link passes; and padding is checked only where a frame goes bare
    assert "TestSwappingUdp::test_datagram_idle_receive_returns_none" not in failed
    assert "TestPaddedUdp::test_datagram_frames_beyond_max_frame_cross_fragmented_by_the_core" \
        not in failed
