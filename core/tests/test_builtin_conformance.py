"""The built-in plugins run the plugin kit's conformance suites, like any other plugin."""

from __future__ import annotations

from rosgate_testing import CipherConformance, CodecConformance, PacketizerConformance

from rosgate.builtin import CdrCodec, Fragments, NoCipher


class TestCdrConformance(CodecConformance):
    codec = CdrCodec


class TestNoneConformance(CipherConformance):
    cipher = NoCipher


class TestFragmentsConformance(PacketizerConformance):
    packetizer = Fragments
    cuts_every_frame = False  # the link sends a frame that fits whole
