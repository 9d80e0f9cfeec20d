"""The built-in plugins run the plugin kit's conformance suites, like any other plugin."""

from __future__ import annotations

from rosgate_testing import CipherConformance, CodecConformance

from rosgate.builtin import CdrCodec, NoCipher


class TestCdrConformance(CodecConformance):
    codec = CdrCodec


class TestNoneConformance(CipherConformance):
    cipher = NoCipher
