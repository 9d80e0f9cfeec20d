"""A smoke run of the soak (tests/soak/soak.py) inside ``make test``, so it keeps working:
15 s of attacks after 6 s of traffic only (every attack: the idle-connection flood three times,
about fifteen client sessions, one in four left to expire), every message delivered, fds and
threads back where they were. Memory is judged by ``make soak`` (30 minutes), not by a run
this short."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.mark.alone  # 1,000 msg/s over UDP: loses datagrams when other tests starve it of the cores
@pytest.mark.timeout(300)
def test_a_short_soak_passes(tmp_path, domain):
    out = tmp_path / "soak.md"
    env = dict(os.environ, ROSGATE_SOAK_DOMAINS=f"{domain()},{domain()}")
    done = subprocess.run([sys.executable, str(HERE / "soak.py"), "--minutes", "0.25",
                           "--warmup", "0.1", "--every", "5", "--rss-limit", "1",
                           "--out", str(out)], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert out.read_text().rstrip().endswith("PASS")
