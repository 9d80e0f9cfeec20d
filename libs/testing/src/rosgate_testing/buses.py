"""The conformance suite of bus transports (:mod:`rosgate_fleet.session`): publish and subscribe
by key, queries, liveliness, closing, and rosgate-fleet's :class:`rosgate_fleet.BusLink` over
them."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from typing import Any, ClassVar

import pytest
from rosgate_fleet import BusLink, BusSession, FleetTransport

from rosgate.config import PRIORITIES

from .helpers import TIMEOUT, Closing, Frames, assert_registered, frame_of

PRIORITY_DEFAULT = PRIORITIES["data"]


class Inbox:
    """What a callback was given, from whichever thread; wait for a count."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        self._cond = threading.Condition()

    def __call__(self, *item: Any) -> None:
        with self._cond:
            self.items.append(item if len(item) > 1 else item[0])
            self._cond.notify_all()

    def wait(self, count: int, timeout: float = TIMEOUT) -> list[Any]:
        with self._cond:
            self._cond.wait_for(lambda: len(self.items) >= count, timeout)
            return list(self.items)


class BusConformance:
    """The conformance suite of a bus transport. Set :attr:`transport` and :attr:`options`, or
    override the ``plugin`` fixture when the sessions of a test need something first (a router
    to meet at, a port of their own): every session the suite opens with ``plugin`` must see
    every other."""

    #: the FleetTransport subclass under test, or a factory taking the options
    transport: ClassVar[Callable[[Mapping[str, Any]], FleetTransport]]
    #: the plugin's options, as under ``plugins:`` in bringup.yaml
    options: ClassVar[Mapping[str, Any]] = {}

    @pytest.fixture
    def plugin(self) -> FleetTransport:
        return type(self).transport(dict(self.options))

    @pytest.fixture
    def closing(self) -> Iterator[Closing]:
        closing = Closing()
        yield closing
        closing.close_all()

    @pytest.fixture
    def open_session(self, plugin: FleetTransport, closing: Closing) -> Callable[[], BusSession]:
        names = iter(f"kit{n}" for n in range(1000))
        return lambda: closing(plugin.open(next(names)))

    @pytest.fixture
    def space(self) -> str:
        """A key space of the test's own."""
        return f"kit/{uuid.uuid4().hex[:12]}"

    @staticmethod
    def _settled(put: Callable[[bytes], None], inbox: Inbox, probe: bytes = b"probe") -> int:
        """Publish ``probe`` until one arrives (declarations take a moment to spread); how many
        items the inbox holds then."""
        deadline = time.monotonic() + TIMEOUT
        while True:
            put(probe)
            if inbox.wait(1, 0.1):
                time.sleep(0.1)  # the probes still on their way
                return len(inbox.items)
            assert time.monotonic() < deadline, "nothing published ever arrived"

    def test_found_through_its_entry_point(self, plugin: FleetTransport) -> None:
        assert isinstance(plugin, FleetTransport)
        assert_registered("transport", type(plugin))

    def test_frames_cross_byte_exact_with_their_concrete_key(self, plugin, open_session, space):
        a, b = open_session(), open_session()
        inbox = Inbox()
        b.subscribe(f"{space}/*", inbox)
        pub = a.publisher(f"{space}/x", reliable=True, priority=PRIORITY_DEFAULT)
        start = self._settled(pub.put, inbox)
        frames = [frame_of(size, seed) for seed, size in enumerate([1, 2, 1000, 65_536, 1 << 20])]
        for frame in frames:
            pub.put(frame)
        got = inbox.wait(start + len(frames))[start:]
        assert [key for key, _ in got] == [f"{space}/x"] * len(frames)
        assert [frame for _, frame in got] == frames

    def test_a_wildcard_matches_one_chunk_and_a_double_one_any(self, plugin, open_session, space):
        a, b = open_session(), open_session()
        one, many = Inbox(), Inbox()
        b.subscribe(f"{space}/*/x", one)
        b.subscribe(f"{space}/**", many)
        probe = a.publisher(f"{space}/probe/x", reliable=True, priority=PRIORITY_DEFAULT)
        self._settled(probe.put, one)
        self._settled(probe.put, many)
        one.items.clear()
        many.items.clear()
        for key in (f"{space}/r1/x", f"{space}/r1/y/x", f"{space}/r2/x", f"{space}/last"):
            a.publisher(key, reliable=True, priority=PRIORITY_DEFAULT).put(key.encode())
        assert [k for k, _ in many.wait(4)] == [f"{space}/r1/x", f"{space}/r1/y/x",
                                                f"{space}/r2/x", f"{space}/last"]
        assert sorted(k for k, _ in one.items) == [f"{space}/r1/x", f"{space}/r2/x"]

    def test_a_reliable_publisher_keeps_order(self, plugin, open_session, space):
        a, b = open_session(), open_session()
        inbox = Inbox()
        b.subscribe(f"{space}/o", inbox)
        pub = a.publisher(f"{space}/o", reliable=True, priority=PRIORITY_DEFAULT)
        start = self._settled(pub.put, inbox)
        for n in range(500):
            pub.put(n.to_bytes(4, "big"))
        got = [int.from_bytes(f, "big") for _, f in inbox.wait(start + 500)[start:]]
        assert got == list(range(500))

    def test_a_closed_subscription_delivers_nothing_more(self, plugin, open_session, space):
        a, b = open_session(), open_session()
        inbox, other = Inbox(), Inbox()
        handle = b.subscribe(f"{space}/c", inbox)
        b.subscribe(f"{space}/c", other)
        pub = a.publisher(f"{space}/c", reliable=True, priority=PRIORITY_DEFAULT)
        self._settled(pub.put, inbox)
        handle.close()
        count = len(inbox.items)
        start = self._settled(pub.put, other, b"after")
        pub.put(b"last")
        other.wait(start + 1)
        assert len(inbox.items) == count

    def test_a_query_is_answered_byte_exact_from_another_thread(self, open_session, space):
        a, b = open_session(), open_session()

        def later(key: str, payload: bytes, query: Any) -> None:
            def answer() -> None:  # the core answers later, from its own thread
                query.reply(payload[::-1] + key.encode())
                query.close()
            threading.Thread(target=answer, daemon=True).start()

        b.serve(f"{space}/srv", later)
        request = frame_of(70_000, 3)
        deadline = time.monotonic() + TIMEOUT
        while True:  # until the queryable has spread: a query nobody serves is over at once
            replies, done = Inbox(), Inbox()
            a.query(f"{space}/srv", request, TIMEOUT, replies, done)
            if done.wait(1) == [1]:
                break
            assert done.items == [0] and time.monotonic() < deadline, "never answered"
        assert replies.items == [request[::-1] + f"{space}/srv".encode()]

    def test_a_query_nobody_serves_is_over_at_once_without_answers(self, open_session, space):
        a, _ = open_session(), open_session()
        replies, done = Inbox(), Inbox()
        started = time.monotonic()
        a.query(f"{space}/nobody", b"x", 10.0, replies, done)
        assert done.wait(1) == [0]
        assert time.monotonic() - started < 5.0, "no server must not cost the whole timeout"
        assert replies.items == []

    def test_a_query_closed_without_an_answer_is_over_without_answers(self, open_session, space):
        a, b = open_session(), open_session()
        seen = Inbox()

        def refuse(key: str, payload: bytes, query: Any) -> None:
            seen(key)
            query.close()

        b.serve(f"{space}/refuse", refuse)
        replies = Inbox()
        deadline = time.monotonic() + TIMEOUT
        while True:
            done = Inbox()
            a.query(f"{space}/refuse", b"x", 10.0, replies, done)
            assert done.wait(1, 10.0) == [0]
            if seen.items:
                break
            assert time.monotonic() < deadline, "the queryable was never reached"
        assert replies.items == []

    def test_an_unanswered_query_is_over_after_its_timeout(self, open_session, space):
        a, b = open_session(), open_session()
        held = Inbox()
        b.serve(f"{space}/hold", held)  # keeps every query, answers none
        replies = Inbox()
        deadline = time.monotonic() + TIMEOUT
        while True:
            done = Inbox()
            started = time.monotonic()
            a.query(f"{space}/hold", b"x", 0.5, replies, done)
            assert done.wait(1, 5.0) == [0]
            if held.items:
                break
            assert time.monotonic() < deadline, "the queryable was never reached"
        assert 0.4 < time.monotonic() - started < 4.0
        assert replies.items == []
        for _, _, query in held.items:
            query.close()

    def test_tokens_are_reported_present_arriving_and_leaving(self, open_session, space):
        a, b, c = open_session(), open_session(), open_session()
        a.token(f"{space}/a/@alive")
        spread = Inbox()
        c.watch(f"{space}/*/@alive", spread)  # a token takes a moment to spread too
        assert spread.wait(1) == [(f"{space}/a/@alive", True)]
        changes = Inbox()
        b.watch(f"{space}/*/@alive", changes)
        assert changes.wait(1) == [(f"{space}/a/@alive", True)]  # there before the watch
        token = c.token(f"{space}/c/@alive")
        assert changes.wait(2)[1] == (f"{space}/c/@alive", True)
        token.close()
        assert changes.wait(3)[2] == (f"{space}/c/@alive", False)
        a.close()  # a holder that goes takes its token along
        assert changes.wait(4)[3] == (f"{space}/a/@alive", False)

    def test_a_process_that_exits_without_closing_does_not_hang(self, plugin, space):
        """Bus libraries with threads of their own (zenoh's callback threads are not daemons)
        can keep a process from ever exiting: the core closes its sessions, but a crash or a
        forgotten close must not hang the process."""
        cls = type(plugin)
        script = (f"import json, sys\nfrom {cls.__module__} import {cls.__qualname__} as T\n"
                  f"t = T(json.loads(sys.argv[1]))\ns = t.open('exiting')\n"
                  f"s.subscribe('{space}/x', lambda k, f: None)\n"
                  f"s.serve('{space}/q', lambda k, p, q: None)\n"
                  f"s.watch('{space}/*/@alive', lambda k, a: None)\n"
                  f"s.token('{space}/me/@alive')\nprint('open', flush=True)\n")
        options = plugin.options
        table = (dataclasses.asdict(options) if dataclasses.is_dataclass(options)
                 and not isinstance(options, type) else options)
        process = subprocess.run([sys.executable, "-c", script, json.dumps(dict(table))],
                                 capture_output=True, text=True, timeout=30)
        assert process.stdout.strip() == "open", process.stderr
        assert process.returncode == 0, process.stderr

    def test_close_is_prompt_and_leaves_no_thread_behind(self, plugin, space):
        before = {t.ident for t in threading.enumerate()}
        session = plugin.open("closing")
        session.subscribe(f"{space}/x", lambda k, f: None)
        session.serve(f"{space}/q", lambda k, p, q: None)
        session.watch(f"{space}/*/@alive", lambda k, a: None)
        session.token(f"{space}/me/@alive")
        session.query(f"{space}/q", b"", 1.0, lambda p: None, lambda n: None)
        started = time.monotonic()
        session.close()
        assert time.monotonic() - started < 2.0
        deadline = time.monotonic() + TIMEOUT
        while True:
            left = [t for t in threading.enumerate()
                    if t.ident not in before and t.is_alive() and not t.daemon]
            if not left or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        assert left == [], f"threads left behind: {[t.name for t in left]}"

    # -- through the core ---------------------------------------------------------------------

    def test_frames_cross_through_the_core_and_a_full_queue_is_counted(
            self, plugin, open_session, closing, space):
        a, b = open_session(), open_session()
        drops: list[tuple[str, str]] = []
        tx = closing(BusLink(plugin, a, "kit-tx", lambda link, reason, detail: drops.append(
            (reason, detail))))
        rx = closing(BusLink(plugin, b, "kit-rx", lambda link, reason, detail: drops.append(
            (reason, detail)), queue_limit=4))
        received, gate = Frames(), threading.Event()

        def slow(key: str, frame: bytes) -> None:
            gate.wait(TIMEOUT)
            received.on_frame(frame, rx, (key, 0))

        overflowed: list[tuple[str, str]] = []
        rx.subscribe(f"{space}/t", slow, lambda key, reason: overflowed.append((key, reason)))
        outlet = tx.outlet(f"{space}/t", reliable=True, priority=PRIORITY_DEFAULT)
        sent = Frames()
        gate.set()
        probe = Inbox()
        rx.subscribe(f"{space}/t", lambda key, frame: probe(frame), lambda k, r: None)
        self._settled(lambda f: outlet.send(f, sent.sender(1)), probe)
        time.sleep(0.2)
        start = len(received.frames)
        gate.clear()  # the link's thread is now held by the first frame: 4 more fit, then drops
        frames = [frame_of(100, n) for n in range(40)]
        for frame in frames:
            assert outlet.send(frame, sent.sender(1))
        deadline = time.monotonic() + TIMEOUT
        while len(overflowed) < 20 and time.monotonic() < deadline:
            time.sleep(0.02)
        gate.set()
        got = received.wait_count(start + 40 - len(overflowed))[start:]
        assert len(got) + len(overflowed) == 40
        assert {reason for _, reason in overflowed} == {"queue_full"}
        assert all(frame in frames for frame in got)
        assert sent.drops == [] and drops == []

    def test_a_call_crosses_through_the_core_and_a_missing_server_fails_it(
            self, plugin, open_session, closing, space):
        a, b = open_session(), open_session()
        caller_link = closing(BusLink(plugin, a, "kit-caller", lambda *args: None))
        server_link = closing(BusLink(plugin, b, "kit-server", lambda *args: None))

        def serve(frame: bytes, answerer: Any, source: Any) -> None:
            assert answerer.send(b"answer:" + frame, sent.sender(2), source)

        sent = Frames()
        server_link.serve(f"{space}/call", serve, hold=TIMEOUT)
        answers = Frames()
        caller = caller_link.caller(f"{space}/call", timeout=TIMEOUT)
        caller.on_answer = answers.on_frame
        deadline = time.monotonic() + TIMEOUT
        calls = Frames()
        while not answers.frames:
            assert time.monotonic() < deadline, "no call was ever answered"
            assert caller.send(b"request", calls.sender(2))
            answers.wait_count(1, 0.5)
        assert answers.frames[0] == b"answer:request"
        nobody = caller_link.caller(f"{space}/nobody", timeout=TIMEOUT)
        nobody.on_answer = answers.on_frame
        lost = Frames()
        assert nobody.send(b"request", lost.sender(3))
        deadline = time.monotonic() + TIMEOUT
        while not lost.drops and time.monotonic() < deadline:
            time.sleep(0.02)
        assert lost.drops == [(3, "no_server")]
        assert sent.drops == []
