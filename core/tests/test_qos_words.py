"""A topic's reliability read from the file's QoS words, as rclpy's own profiles have it: what
the resolver decides with (a reliable topic's frames wait out a link loss) without rclpy."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
from rclpy.qos import ReliabilityPolicy

from rosgate.config import QOS_PROFILES
from rosgate.rostypes import is_reliable, qos_profile

SPECS = [1, 10, 1000, *QOS_PROFILES, {"depth": 5}, {"reliability": "reliable"},
         {"reliability": "best_effort"}, {"durability": "transient_local"},
         {"reliability": "best_effort", "durability": "transient_local", "history": "keep_all"}]


@pytest.mark.parametrize("spec", SPECS, ids=str)
def test_reliable_unless_rclpy_s_profile_is_best_effort(spec):
    assert is_reliable(spec) is (qos_profile(spec).reliability != ReliabilityPolicy.BEST_EFFORT)


def test_the_words_cover_both_answers():
    assert not is_reliable("sensor_data") and not is_reliable({"reliability": "best_effort"})
    assert is_reliable("system_default") and is_reliable("best_available") and is_reliable(10)


def test_checking_a_file_of_string_topics_does_not_load_rclpy(tmp_path):
    """In a fresh process: rclpy loads the ROS client library (tens of milliseconds) and
    rosgate check has no use for it here."""
    path = tmp_path / "bringup.yaml"
    path.write_text(textwrap.dedent("""\
        bridge: {name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, insecure: true}
        topics:
          - {topic: /a, type: std_msgs/msg/String, direction: transmit, port: 12001}
          - {topic: /b, type: std_msgs/msg/String, direction: receive, port: 12002,
             qos: sensor_data}
        """))
    code = ("import sys; from rosgate.cli import main; status = main(['check', sys.argv[1]]); "
            "print(status, sorted(m for m in sys.modules if m.split('.')[0] == 'rclpy'))")
    result = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                            text=True, timeout=60, check=True)
    assert result.stdout.splitlines()[-1] == "0 []", (result.stdout, result.stderr)
