"""What the benchmark's overload and shaped-link measurements rest on, checked without timing
anything (bench/ measures; this only keeps its parts from rotting unseen):

- the files bench.py and bench/shaped.py write for the default file with the real_time Twist
  beside the measured topic pass ``rosgate check`` (the server's policy lets both topics in,
  the Twist's priority is a class the schema knows);
- "newest" (of what arrived during a trial's last quarter, the share sent in it) tells a path
  that queues from one that sheds the oldest.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

BENCH = Path(__file__).resolve().parents[1] / "bench"
sys.path.insert(0, str(BENCH))

import endpoints  # noqa: E402
from processes import ROSGATE, TWIST_TOPIC, Route, bringup_files  # noqa: E402

MS = 1_000_000


def test_the_default_file_with_the_twist_passes_check(tmp_path):
    best_effort = Route("udp", cipher="aead", roles="session", max_frame=None,
                        reliability="best_effort")
    a, b = bringup_files(best_effort, "std_msgs/msg/String", 1000, tmp_path, "best_effort",
                         port=12345, twist=True, host=("10.201.0.2", "10.201.0.2"))
    client, server = yaml.safe_load(a.read_text()), yaml.safe_load(b.read_text())
    twist = next(t for t in client["topics"] if t["topic"] == TWIST_TOPIC)
    assert twist["priority"] == "real_time" and twist["type"] == "geometry_msgs/msg/Twist"
    assert client["bridge"]["server"] == "10.201.0.2:12345" == server["bridge"]["server"]
    allowed = {t["name"] for t in server["clients"]["bench_a"]["topics"]}
    assert allowed == {"/bench", TWIST_TOPIC}
    for path in (a, b):
        checked = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                                 timeout=60)
        assert checked.returncode == 0, checked.stderr
        assert "INSECURE" not in checked.stderr


def test_newest_tells_a_queue_from_a_path_that_sheds_the_oldest():
    """A 1 s trial at 1,000 msg/s, its last quarter from 750 ms: one path delivers every
    message 300 ms late (a queue), the other every second message 5 ms late (shedding)."""
    sent = [i * MS for i in range(1000)]
    tail, end = 750 * MS, 1000 * MS

    queued = endpoints.tail([s + 300 * MS for s in sent], sent, tail, end)
    assert queued == {"tail": 251, "tail_fresh": 0}  # sent 450-700 ms: none of the newest

    kept = sent[::2]
    shed = endpoints.tail([s + 5 * MS for s in kept], kept, tail, end)
    assert shed == {"tail": 125, "tail_fresh": 123}  # sent 746 and 748 ms: older
