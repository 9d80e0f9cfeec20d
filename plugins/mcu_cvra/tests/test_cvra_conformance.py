"""The CVRA call pattern runs the kit's suite of service framings; tests/test_mcu.py runs it end
to end against a board simulated as CVRA's firmware writes."""

from __future__ import annotations

from rosgate_codec_msgpack import MsgpackCodec
from rosgate_mcu_cvra import SerialDatagramCalls
from rosgate_testing import ServiceFramingConformance


class TestSerialDatagramConformance(ServiceFramingConformance):
    service_framing = SerialDatagramCalls
    codec = MsgpackCodec
