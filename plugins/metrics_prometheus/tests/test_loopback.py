"""Which addresses the endpoint takes without metrics_public: loopback only."""

import pytest
from rosgate_metrics_prometheus import is_loopback


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "::1", "localhost"])
def test_loopback(host):
    assert is_loopback(host)


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.20", "10.0.0.1", "robot.local"])
def test_not_loopback(host):
    assert not is_loopback(host)
