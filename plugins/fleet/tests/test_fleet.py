"""rosgate-fleet without zenoh: found through its entry point, the keys it gives and refuses, and
its bus link over an in-memory session — order, a full queue counted, held queries closed, late
answers counted, everything withdrawn at close. (Over a real bus: the zenoh plugin's tests and
tests/test_zenoh_*.py.)"""

from __future__ import annotations

import threading
from collections.abc import Callable

import pytest
from rosgate_fleet import BusLink, BusWiring, FleetTransport, check_key

from rosgate import BusTransport, ConfigError, Drop, ServiceConfig, TopicConfig
from rosgate.config import loads
from rosgate.plugins import Plugins

TIMEOUT = 5.0


class Held:
    """A declaration of the in-memory session; ``closed`` once withdrawn."""

    def __init__(self) -> None:
        self.closed = False

    def close(self) -> None:
        self.closed = True


class Query(Held):
    def __init__(self) -> None:
        super().__init__()
        self.replies: list[bytes] = []

    def reply(self, payload: bytes) -> None:
        self.replies.append(payload)


class Session:
    """A bus session in memory: the test calls the handlers as a bus library's thread would."""

    def __init__(self) -> None:
        self.samples: dict[str, Callable[[str, bytes], None]] = {}
        self.queries: dict[str, Callable[[str, bytes, Query], None]] = {}
        self.handles: list[Held] = []
        self.closed = False

    def _held(self) -> Held:
        self.handles.append(Held())
        return self.handles[-1]

    def subscribe(self, key_expr: str, on_sample: Callable[[str, bytes], None]) -> Held:
        self.samples[key_expr] = on_sample
        return self._held()

    def serve(self, key: str, on_query: Callable[[str, bytes, Query], None]) -> Held:
        self.queries[key] = on_query
        return self._held()

    def token(self, key: str) -> Held:
        return self._held()

    def close(self) -> None:
        self.closed = True


class Bus(FleetTransport):
    name = "membus"

    def open(self, name):
        return Session()


class Entries:
    """What the link's thread handed over, waited for with a timeout."""

    def __init__(self) -> None:
        self.items: list[tuple] = []
        self.cond = threading.Condition()

    def __call__(self, *item) -> None:
        with self.cond:
            self.items.append(item)
            self.cond.notify_all()

    def wait(self, count: int) -> list[tuple]:
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.items) >= count, TIMEOUT), self.items
            return list(self.items)


@pytest.fixture
def link():
    made = BusLink(Bus(None), Session(), "membus", lambda link, reason, detail: None,
                   queue_limit=3)
    yield made
    made.close()


def test_found_through_its_entry_point_as_the_bus_role_fleet():
    registration = Plugins.discover().get("bus_role", "fleet")
    assert registration is not None
    assert (registration.cls, registration.distribution) == (BusWiring, "rosgate-fleet")
    assert BusTransport.role == "fleet"  # what a bus transport asks for unless it says otherwise


@pytest.mark.parametrize("key, problem", [
    ("", "'' is not a key: no leading or trailing '/', not empty"),
    ("/a/b", "'/a/b' is not a key: no leading or trailing '/', not empty"),
    ("a//b", "'a//b' is not a key: chunk '' is empty or holds '*', '$', '?' or '#' (a wildcard "
             "is '*' or '**' alone)"),
    ("a/b*", "'a/b*' is not a key: chunk 'b*' is empty or holds '*', '$', '?' or '#' (a "
             "wildcard is '*' or '**' alone)"),
])
def test_check_key_names_the_rule_a_key_breaks(key, problem):
    with pytest.raises(ValueError) as info:
        check_key(key)
    assert str(info.value) == problem


def test_check_key_takes_chunks_and_wildcards():
    assert [check_key(k) for k in ("fleet/r1/scan", "fleet/*/scan", "fleet/**", "r/@alive")] == [
        "fleet/r1/scan", "fleet/*/scan", "fleet/**", "r/@alive"]


def test_default_keys_and_tokens_follow_the_prefix():
    bus = Bus(None)
    bus.prefix = "acme"
    assert bus.default_key("r1", "/scan/front", bare=False) == "acme/r1/scan/front"
    assert bus.default_key("r1", "/scan/front", bare=True) == "scan/front"
    assert bus.alive_key("r1") == "acme/r1/@alive"


def entry(fields: str, section: str = "topics") -> TopicConfig | ServiceConfig:
    """One entry of a peer file on the in-memory bus, as the configuration loads it."""
    cfg = loads(f"bridge: {{name: r1, role: peer, defaults: {{transport: membus}}}}\n"
                f"{section}:\n  - {{{fields}}}\n", file="bringup.yaml")
    return (cfg.topics or cfg.services)[0]


def topic(name: str, remote: str | None = None) -> TopicConfig | ServiceConfig:
    return entry(f"topic: '{name}', type: std_msgs/msg/String, direction: transmit"
                 + (f", remote: '{remote}'" if remote else ""))


def test_an_entry_s_key_is_its_remote_or_the_default_key():
    bus = Bus(None)
    assert BusWiring.key(bus, topic("/scan"), "r1") == "rosgate/r1/scan"
    assert BusWiring.key(bus, topic("/scan", "fleet/r1/s"), "r1") == "fleet/r1/s"
    service = entry("service: /reset, type: std_srvs/srv/Trigger, direction: receive",
                    "services")
    assert BusWiring.key(bus, service, "r1") == "rosgate/r1/reset"


def test_an_entry_the_bus_cannot_key_is_refused_at_its_field():
    class Picky(Bus):
        def check_key(self, key):
            if "x" in key:
                raise ValueError(f"{key!r}: this bus takes no x")
            return key

    bus = Picky(None)
    for entry_, field in [(topic("/scan", "fleet/x/s"), "remote"), (topic("/x"), "topic")]:
        with pytest.raises(ConfigError) as info:
            BusWiring.key(bus, entry_, "r1")
        assert (info.value.key, info.value.fix) == (field, "write remote: as parts separated by "
                                                    "single '/', e.g. remote: fleet/robot1/scan")
    assert info.value.message == "'rosgate/r1/x': this bus takes no x"
    bus = Bus(None)
    with pytest.raises(ConfigError) as info:
        BusWiring.key(bus, topic("/{robot}/scan"), "r1")
    assert (info.value.key, info.value.message) == (
        "topic", "membus takes no placeholders such as {robot}")


def test_a_bus_that_is_no_fleet_transport_is_refused_at_the_entry_s_transport():
    class Other(BusTransport):
        name = "other"

        def open(self, name):
            raise AssertionError

    with pytest.raises(ConfigError) as info:
        BusWiring.key(Other(None), topic("/scan"), "r1")
    assert info.value.key == "transport"
    assert info.value.message == ("other asks for the bus role fleet but is no "
                                  "rosgate_fleet.FleetTransport, whose keys that role uses")


def test_frames_reach_their_handler_in_order_on_the_link_s_thread(link):
    got = Entries()
    threads: list[str] = []
    link.subscribe("k/*", lambda key, frame: (threads.append(threading.current_thread().name),
                                              got(key, frame)), lambda key, reason: None)
    deliver = link.session.samples["k/*"]
    for i in range(3):
        deliver(f"k/{i}", bytes([i]) * 4)
    assert got.wait(3) == [("k/0", b"\0" * 4), ("k/1", b"\1" * 4), ("k/2", b"\2" * 4)]
    assert threads == ["rx-membus"] * 3


def test_what_arrives_while_the_queue_is_full_is_counted_against_its_subscription(link):
    entered, release = threading.Event(), threading.Event()
    got = Entries()
    dropped = Entries()

    def slow(key: str, frame: bytes) -> None:
        entered.set()
        release.wait(TIMEOUT)
        got(key, frame)

    link.subscribe("k", slow, dropped)
    deliver = link.session.samples["k"]
    deliver("k", b"first")
    assert entered.wait(TIMEOUT)  # taken by the link's thread, which now waits
    got_first = threading.Event()
    link.call_later(got_first.set)
    for i in range(3):  # the queue holds 3: the call above and two frames
        deliver("k", bytes([i]))
    release.set()
    assert got_first.wait(TIMEOUT)
    assert dropped.wait(1) == [("k", Drop.QUEUE_FULL)]
    assert [frame for _, frame in got.wait(3)] == [b"first", b"\0", b"\1"]


def test_a_query_nobody_answers_is_closed_unanswered_after_its_hold(link):
    heard = Entries()
    link.serve("svc", lambda frame, answerer, source: heard(frame, source), hold=0.3)
    query = Query()
    link.session.queries["svc"]("svc", b"call", query)
    ((frame, source),) = heard.wait(1)
    assert (frame, source) == (b"call", ("svc", 1))
    deadline = threading.Event()
    assert not deadline.wait(0.1) and not query.closed  # held while its caller waits
    for _ in range(int(TIMEOUT / 0.05)):
        if query.closed:
            break
        deadline.wait(0.05)
    assert query.closed and query.replies == []


class Sender:
    def __init__(self) -> None:
        self.drops: list[tuple] = []

    def drop(self, reason, detail="") -> None:
        self.drops.append((reason, detail))


def test_an_answer_goes_to_its_query_once_and_a_late_one_is_counted(link):
    heard = Entries()
    link.serve("svc", lambda frame, answerer, source: heard(answerer, source), hold=TIMEOUT)
    query = Query()
    link.session.queries["svc"]("svc", b"call", query)
    ((answerer, source),) = heard.wait(1)
    sender = Sender()
    assert answerer.send(b"answer", sender, source) is True
    assert (query.replies, query.closed, sender.drops) == ([b"answer"], True, [])
    assert answerer.send(b"again", sender, source) is False
    assert sender.drops == [(Drop.LATE_ANSWER, "the query on svc was closed before the answer")]
    assert query.replies == [b"answer"]


def test_close_withdraws_every_declaration_closes_held_queries_and_the_session(link):
    frames, dropped = Entries(), Entries()
    link.subscribe("k", frames, dropped)
    link.token("r1/@alive")
    link.serve("svc", lambda frame, answerer, source: None, hold=TIMEOUT)
    query = Query()
    link.session.queries["svc"]("svc", b"call", query)
    session = link.session
    link.close()
    assert [h.closed for h in session.handles] == [True, True, True]
    assert query.closed and session.closed
    session.samples["k"]("k", b"late")  # a closed link queues nothing more: counted instead
    assert dropped.wait(1) == [("k", Drop.QUEUE_FULL)]
    assert frames.items == []
