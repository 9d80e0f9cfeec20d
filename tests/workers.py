"""make test's parallel workers (pytest-xdist): each one's share of the run's DDS domains and
ports, and the turns that let a test run alone (tests/conftest.py puts them to use)."""

from __future__ import annotations

import fcntl
from pathlib import Path

import pytest


def worker_share(first: int, last: int, worker: str, workers: int) -> tuple[int, int]:
    """The domains of one pytest-xdist worker (``gw0``, ``gw1``...): an equal slice of the run's."""
    size = (last - first + 1) // workers
    if size < 4:
        raise pytest.UsageError(f"ROSGATE_TEST_DOMAINS={first}-{last} is too few domains for "
                                f"{workers} workers: give at least 4 per worker")
    start = first + int(worker.removeprefix("gw")) * size
    return start, start + size - 1


def domain_ports(first: int, last: int) -> tuple[int, int]:
    """The ports that go with domains FIRST-LAST: 27 per domain, below 7400, where DDS's own
    ports start (7400 + 250 per domain) and far from the kernel's ephemeral ports, so runs
    and workers with domains of their own also get ports of their own."""
    return 1024 + 27 * first, 1024 + 27 * last + 26


class Turns:
    """Between the workers of one run: a test marked ``alone`` runs while no other test does
    (heavy on the cores or timed, so another's load would fail it); the others run side by side.
    A readers-writer lock on files of the run's temporary folder: every other test holds the
    shared lock, an ``alone`` one the exclusive lock, and the turnstile before it keeps new
    tests from starting while an ``alone`` test waits its turn."""

    def __init__(self, folder: Path):
        self.turnstile = open(folder / "turnstile.lock", "a+")  # open for the run
        self.tests = open(folder / "tests.lock", "a+")

    @pytest.hookimpl(wrapper=True, tryfirst=True)  # outside the timeout: waits are no test time
    def pytest_runtest_protocol(self, item: pytest.Item, nextitem: pytest.Item | None):
        alone = item.get_closest_marker("alone") is not None
        fcntl.flock(self.turnstile, fcntl.LOCK_EX)
        try:
            fcntl.flock(self.tests, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            fcntl.flock(self.turnstile, fcntl.LOCK_UN)
        try:
            return (yield)
        finally:
            fcntl.flock(self.tests, fcntl.LOCK_UN)


def alone_first(items: list[pytest.Item]) -> None:
    """The run's ``alone`` tests first, in their order, then the others in theirs. An ``alone``
    test that comes up mid-run waits, with every worker held at the turnstile, until the tests
    the other workers are running end (a long one keeps the whole machine waiting); at the
    start nothing runs yet, so the ``alone`` tests take their turns back to back and cost their
    own time only."""
    items.sort(key=lambda item: item.get_closest_marker("alone") is None)


def take_turns(config: pytest.Config) -> None:
    """In a pytest-xdist worker (whose basetemp is the run's, then ``popen-gwN``), take turns
    with the run's other workers; in a run without workers there is nothing to share."""
    if hasattr(config, "workerinput"):
        config.pluginmanager.register(Turns(Path(config.option.basetemp).parent), "rosgate-turns")
