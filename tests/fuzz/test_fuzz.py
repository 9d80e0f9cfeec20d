"""The fuzz campaign inside ``make test``: the committed seeds and every past finding replayed
through each target, and a short campaign (10^4 generated and mutated inputs per target, a
fixed seed). ``make fuzz`` runs the long one (10^6 per target)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
import targets

HERE = Path(__file__).parent
# every decoder that takes bytes from the network (issue 10)
DECODERS = {"envelope", "reassembly", "stream_framing", "serial_datagram", "control_message",
            "control_depth", "cvra_name_and_map", "msgpack_codec", "cbor_codec", "cdr_check"}


def inputs(name: str) -> list[Path]:
    return sorted([*(HERE / "corpus" / name).glob("*"), *(HERE / "regressions" / name).glob("*")])


def test_every_decoder_has_a_target_and_seeds():
    assert set(targets.TARGETS) >= DECODERS
    for name in targets.TARGETS:
        assert inputs(name), f"no seeds for {name}: run tests/fuzz/seeds.py"


@pytest.mark.parametrize("name", sorted(targets.TARGETS))
def test_seeds_and_past_findings_replay_cleanly(name):
    run = targets.TARGETS[name]
    targets.warm(run)
    for path in inputs(name):
        start = time.thread_time()
        run(path.read_bytes())
        assert time.thread_time() - start < 0.1, f"{path.relative_to(HERE)} took too long"


@pytest.mark.timeout(900)
def test_a_short_campaign_finds_nothing():
    done = subprocess.run([sys.executable, str(HERE / "campaign.py"), "--runs", "10000",
                           "--seed", "1"], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
