"""make test's parallel workers: each gets DDS domains and ports of its own, carved out of the
run's ROSGATE_TEST_DOMAINS, so two workers' tests never hear each other nor share a port."""

from __future__ import annotations

import os

import pytest
from conftest import _FIRST, _LAST, next_domain
from workers import alone_first, domain_ports, worker_share


def test_workers_share_the_domains_without_overlap_and_each_gets_its_ports():
    shares = [worker_share(20, 119, f"gw{i}", 4) for i in range(4)]
    assert shares == [(20, 44), (45, 69), (70, 94), (95, 119)]
    ports = [domain_ports(*share) for share in shares]
    assert ports == [(1564, 2238), (2239, 2913), (2914, 3588), (3589, 4263)]
    assert domain_ports(232, 232)[1] < 7400, "below the first DDS port of domain 0"


def test_too_few_domains_for_the_workers_is_a_usage_error_that_says_what_to_give():
    with pytest.raises(pytest.UsageError, match="20-29 is too few domains for 3 workers"):
        worker_share(20, 29, "gw0", 3)


def test_this_process_uses_its_own_share():
    if "PYTEST_XDIST_WORKER" in os.environ:
        run = tuple(int(n) for n in os.environ.get("ROSGATE_TEST_DOMAINS", "20-119").split("-"))
        assert (_FIRST, _LAST) == worker_share(*run, os.environ["PYTEST_XDIST_WORKER"],
                                               int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    domains = {next_domain() for _ in range(_LAST - _FIRST + 1)}
    assert domains == set(range(_FIRST, _LAST + 1))
    assert os.environ["ROSGATE_TEST_PORTS"] == "{}-{}".format(*domain_ports(_FIRST, _LAST))


TIMED = '''
import os
import time

import pytest


def record(name):
    start = time.monotonic()
    time.sleep(0.4)
    with open(os.environ["TURNS_LOG"], "a") as log:
        log.write(f"{name} {start} {time.monotonic()}\\n")


@pytest.mark.alone
def test_alone():
    record("alone")


@pytest.mark.parametrize("n", range(4))
def test_other(n):
    record(f"other{n}")
'''


def test_an_alone_test_runs_while_no_other_does_and_the_others_side_by_side(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "conftest.py").write_text(
        f"import sys\nsys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from workers import take_turns as pytest_configure  # noqa: E402, F401\n")
    (tmp_path / "test_timed.py").write_text(TIMED)
    log = tmp_path / "log"
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider",
         "-p", "no:rosgate_testing", "-W", "ignore::pytest.PytestUnknownMarkWarning",
         "--basetemp", str(tmp_path / "t"),
         str(tmp_path / "test_timed.py")],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env=dict(os.environ, TURNS_LOG=str(log)))
    assert done.returncode == 0, done.stdout + done.stderr
    spans = {name: (float(a), float(b)) for name, a, b in
             (line.split() for line in log.read_text().splitlines())}
    assert set(spans) == {"alone", *(f"other{n}" for n in range(4))}
    alone = spans.pop("alone")
    for name, (start, end) in spans.items():
        assert end <= alone[0] or start >= alone[1], f"{name} ran beside the alone test"
    others = sorted(spans.values())
    assert any(b[0] < a[1] for a, b in zip(others, others[1:], strict=False)), \
        "the other tests never ran side by side"


def test_the_alone_tests_come_first_and_every_test_keeps_its_order_among_its_kind():
    class Item:
        def __init__(self, name: str, alone: bool):
            self.name, self.alone = name, alone

        def get_closest_marker(self, name: str) -> object | None:
            return object() if name == "alone" and self.alone else None

    items = [Item("a", False), Item("b", True), Item("c", False), Item("d", True), Item("e", False)]
    alone_first(items)
    assert [item.name for item in items] == ["b", "d", "a", "c", "e"]
