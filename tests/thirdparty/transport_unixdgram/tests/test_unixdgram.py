"""A third party's tests of its own transport: the plugin kit's conformance suite, and what is
particular to this link (where its sockets live, its one option)."""

from __future__ import annotations

import itertools
import os

import pytest
from rosgate_testing import TransportConformance
from rosgate_transport_unixdgram import UnixDatagramTransport

from rosgate import OptionError


class TestUnixDatagramConformance(TransportConformance):
    transport = UnixDatagramTransport
    options = {"max_frame": 4096}  # small, so the core's fragmentation is exercised hard

    @pytest.fixture
    def address(self, tmp_path):
        """Addresses are (directory, number): sockets in a folder of the test's own."""
        numbers = itertools.count(1)
        return lambda: (str(tmp_path), next(numbers))


def test_the_socket_file_is_made_and_removed(tmp_path):
    endpoint = UnixDatagramTransport({}).bind((str(tmp_path), 5))
    assert os.path.exists(tmp_path / "5.sock")
    endpoint.close()
    assert not os.path.exists(tmp_path / "5.sock")


@pytest.mark.parametrize("options, key", [({"max_frame": 10}, "max_frame"),
                                          ({"max_frame": "big"}, "max_frame"),
                                          ({"mtu": 100}, "mtu")])
def test_bad_options(options, key):
    with pytest.raises(OptionError) as info:
        UnixDatagramTransport(options)
    assert info.value.key == key
