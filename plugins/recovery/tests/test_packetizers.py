"""fec and retransmit: the plugin kit's packetizer suite — frames cross whole and once, their
cost is what they cut, and both bring every frame through losses — and fec's option."""

from __future__ import annotations

import pytest
from rosgate_recovery import Fec, Retransmit
from rosgate_testing import PacketizerConformance

from rosgate import OptionError
from rosgate.options import parse


class TestFecConformance(PacketizerConformance):
    packetizer = Fec
    options = {"overhead": 0.3}
    recovers = True


class TestRetransmitConformance(PacketizerConformance):
    packetizer = Retransmit
    recovers = True


class TestRetransmitOnALossierPathConformance(PacketizerConformance):
    packetizer = Retransmit
    recovers = True
    loss = 0.2


@pytest.mark.parametrize("options, message", [
    ({"overhead": 0}, "must be more than 0, not 0"),
    ({"overhead": 1.5}, "expected a number at most 1, got 1.5"),
    ({"overhead": "lots"}, "expected a number at most 1, got 'lots'"),
])
def test_wrong_overheads(options, message):
    with pytest.raises(OptionError) as error:
        parse(Fec, options)
    assert (error.value.key, error.value.message) == ("overhead", message)
