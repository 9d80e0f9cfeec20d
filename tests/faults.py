"""The fault proxy of the end-to-end tests: the link emulator's (``rosgate_emulator.faults``),
under the name the tests import it by."""

from rosgate_emulator.faults import FaultProxy, TcpFaults, UdpFaults, UdpRates

__all__ = ["FaultProxy", "TcpFaults", "UdpFaults", "UdpRates"]
