"""A topic's batch window: read from the file, opened by a message, closed by the executor's
loop, and what came in it handed to the link in one call, in order."""

from __future__ import annotations

import inspect
import time
from collections import deque
from pathlib import Path

import pytest

from rosgate.batch import Batches
from rosgate.builtin import CdrCodec, NoCipher
from rosgate.config import TopicConfig, load
from rosgate.errors import ConfigError
from rosgate.keyring import StaticKeys
from rosgate.routes import EnvelopeFraming, TransmitRoute, Warner
from rosgate.spec import Delivery
from rosgate.wire import envelope

HEAD = """\
bridge:
  name: robot1
  role: client
  server: 127.0.0.1:12000
topics:
  - topic: /scan
    type: std_msgs/msg/String
    direction: transmit
"""


def entry(tmp_path: Path, value: str) -> TopicConfig:
    path = tmp_path / "bringup.yaml"
    path.write_text(HEAD + f"    batch: {value}\n")
    return load(path).topics[0]


@pytest.mark.parametrize("value, seconds", [
    ("2ms", 0.002), ("500us", 0.0005), ("0.002", 0.002), ("0", 0.0), ("1.5 ms", 0.0015),
    ("0.1s", 0.1)])
def test_a_window_is_read_with_its_unit(tmp_path, value, seconds):
    assert entry(tmp_path, value).batch == pytest.approx(seconds)


def test_no_window_by_default(tmp_path):
    path = tmp_path / "bringup.yaml"
    path.write_text(HEAD)
    assert load(path).topics[0].batch is None


@pytest.mark.parametrize("value, says", [
    ("2 hours", "expected a duration such as 2ms, got '2 hours'"),
    ("200ms", "a window of 200 ms is outside 0..100 ms"),
    ("-1ms", "expected a duration such as 2ms"),
    ("true", "expected a duration such as 2ms, got True")])
def test_a_wrong_window_names_file_line_key_and_fix(tmp_path, value, says):
    with pytest.raises(ConfigError) as caught:
        entry(tmp_path, value)
    error = caught.value
    assert (error.file, error.line, error.key) == (str(tmp_path / "bringup.yaml"), 9,
                                                   "topics[0].batch")
    assert says in error.message
    assert error.fix == "write a duration up to 100 ms, e.g. batch: 2ms"


# --- the node's open windows --------------------------------------------------------------------

def test_windows_close_when_due_in_any_order():
    batches = Batches()
    closed: list[str] = []
    assert not batches and batches.close_due(0.0) is None
    batches.open(10.002, lambda: closed.append("b"))
    batches.open(10.001, lambda: closed.append("a"))
    assert batches and batches.close_due(10.0) == pytest.approx(0.001)
    assert closed == []
    assert batches.close_due(10.0015) == pytest.approx(0.0005)
    assert closed == ["a"]
    assert batches.close_due(10.5) is None and closed == ["a", "b"] and not batches


# --- a route with a window --------------------------------------------------------------------

class Link:
    datagram = True

    def __init__(self) -> None:
        self.calls: list[list[bytes]] = []

    def send_all(self, frames, sender, to=None) -> int:
        self.calls.append(list(frames))
        return len(frames)

    def forget(self, sender) -> None:
        """What the link queued for a removed route goes (nothing is queued here)."""


def batching(window: float, waiting: deque) -> tuple[TransmitRoute, Link, Batches]:
    fields = inspect.signature(TopicConfig).parameters
    topic = TopicConfig(**{name: None for name, p in fields.items() if p.default is p.empty})
    topic.batch = window
    link = Link()
    route = TransmitRoute(topic, 7, CdrCodec(None, {}), StaticKeys(NoCipher({}, ".")), Warner(),
                          "/scan", Delivery(), framing=EnvelopeFraming(),
                          link=link,  # type: ignore[arg-type]
                          destination=lambda: ("127.0.0.1", 9))
    route.batches = Batches()
    route.entity = object()  # subscribed
    route.take = lambda: (waiting.popleft(), time.time_ns()) if waiting else None
    return route, link, route.batches


def message(i: int) -> bytes:
    return b"\x00\x01\x00\x00" + b"%04d" % i


def test_what_comes_in_a_window_leaves_in_one_call_in_order():
    waiting: deque = deque()
    # a window far longer than this test can be descheduled for: what it asserts of the
    # window's end does not depend on the machine's load
    route, link, batches = batching(10.0, waiting)
    opened = time.monotonic()
    for i in range(3):  # the executor hands them over one by one: the window holds them
        route.on_message(message(i))
    assert link.calls == [] and batches
    waiting.extend(message(i) for i in range(3, 40))  # arrived while the executor slept
    wait = batches.close_due(time.monotonic())
    assert wait is not None and 0 < wait <= 10.0 - (time.monotonic() - opened) + 1e-3
    assert batches.close_due(opened + 10.0001) is None
    assert len(link.calls) == 1  # one call: the link puts them in as few datagrams as fit
    frames = link.calls[0]
    assert [f[envelope.SIZE:] for f in frames] == [message(i) for i in range(40)]
    assert [envelope.unpack(f).seq for f in frames] == list(range(1, 41))
    assert route.counters.sent == 40 and not waiting and not route.pending
    route.on_message(message(40))  # the next message opens the next window
    assert link.calls == [frames] and batches
    batches.close_due(time.monotonic() + 11)
    assert [f[envelope.SIZE:] for f in link.calls[1]] == [message(40)]


def test_no_window_is_todays_path():
    waiting: deque = deque([message(1)])
    route, link, batches = batching(0.0, waiting)
    route.on_message(message(0))
    assert not batches and [[f[envelope.SIZE:] for f in c] for c in link.calls] == [
        [message(0), message(1)]]


def test_a_route_removed_with_its_window_open_sends_nothing():
    waiting: deque = deque([message(1)])
    route, link, batches = batching(0.002, waiting)
    route.on_message(message(0))
    route.entity = None  # as the router does before close
    route.close()
    assert batches.close_due(time.monotonic() + 1) is None
    assert link.calls == [] and route.counters.sent == 0
