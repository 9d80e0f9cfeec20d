"""The built-in plugins run the plugin kit's conformance suites, like any other plugin."""

from __future__ import annotations

from rosgate.builtin import CdrCodec, NoCipher
from rosgate.testing import CipherConformance, CodecConformance


class TestCdrConformance(CodecConformance):
    codec = CdrCodec


class TestNoneConformance(CipherConformance):
    cipher = NoCipher
