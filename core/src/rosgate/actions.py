"""Actions across the link (docs/actions.md): a ROS 2 action *is* three services and two
topics under ``<name>/_action/``, so an ``actions:`` entry becomes those five entries, with the
types rosidl makes for it, and the service and topic routes carry them. ``get_result`` waits as
long as a goal runs (up to an hour); in peer role feedback and status take ``port + 1``.
On a server, a goal belongs to the client that sent it (:class:`Goals`): :class:`ClientGoals`
keeps each client to its own goals unless the rule says ``shared``.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from .config import TIMEOUT_MAX, ActionConfig, ServiceConfig, TopicConfig
from .drops import Drop, Reason

#: the QoS of an action's status and feedback, as rclpy's ActionServer publishes them
STATUS_QOS = {"reliability": "reliable", "durability": "transient_local", "depth": 1}
FEEDBACK_QOS = {"reliability": "reliable", "durability": "volatile", "depth": 10}


def parts(action: ActionConfig) -> list[TopicConfig | ServiceConfig]:
    """The services, then the topics, an action is made of, in the action's words."""
    package, _, name = action.type.split("/")
    calls, reports = action.direction, action.direction.flipped
    topic_port = action.port + 1 if action.port is not None else None

    def service(part: str, type_name: str, timeout: float) -> ServiceConfig:
        return ServiceConfig(f"{action.action}/_action/{part}", type_name, calls,
                             f"{action.remote}/_action/{part}", action.transport, action.codec,
                             action.cipher, action.port, action.framing, timeout,
                             line=action.line, lines=action.lines)

    def topic(part: str, type_name: str, qos: dict) -> TopicConfig:
        return TopicConfig(f"{action.action}/_action/{part}", type_name, reports,
                           f"{action.remote}/_action/{part}", action.transport, action.codec,
                           action.cipher, topic_port, action.framing, qos=dict(qos), qos_given=True,
                           line=action.line, lines=action.lines)

    return [
        service("send_goal", f"{package}/action/{name}_SendGoal", action.timeout),
        service("cancel_goal", "action_msgs/srv/CancelGoal", action.timeout),
        service("get_result", f"{package}/action/{name}_GetResult", TIMEOUT_MAX),
        topic("feedback", f"{package}/action/{name}_FeedbackMessage", FEEDBACK_QOS),
        topic("status", "action_msgs/msg/GoalStatusArray", STATUS_QOS),
    ]



# -- goals belong to the client that sent them (a server's clients; docs/actions.md) ----------
#: action_msgs' numbers: GoalStatus terminal states, CancelGoal's return codes
STATUS_UNKNOWN = 0
ENDED = frozenset({4, 5, 6})  # succeeded, canceled, aborted
CANCEL_UNKNOWN_GOAL = 2
#: seconds an ended goal is remembered: rclpy's action server keeps a result 900 s by default
KEEP_ENDED = 900.0
#: goals of one action the server remembers per client; past it, a new goal is not accepted
GOALS_PER_CLIENT = 1000
NO_GOAL = bytes(16)
Stamp = tuple[int, int]  # a goal's acceptance time as its status says it: (sec, nanosec)


class Goals:
    """Who sent each goal of one action a server serves to its clients: goal id -> client,
    and when the action server accepted it (from its status). Ended goals are forgotten
    :data:`KEEP_ENDED` seconds later, and a client holds at most :data:`GOALS_PER_CLIENT`
    (its oldest ended goal goes first)."""

    def __init__(self, keep: float = KEEP_ENDED, cap: int = GOALS_PER_CLIENT,
                 clock: Callable[[], float] = time.monotonic):
        self.keep, self.cap, self.clock = keep, cap, clock
        self._owner: dict[bytes, str] = {}
        self._stamp: dict[bytes, Stamp] = {}
        self._ended: dict[bytes, float] = {}  # goal id -> when it was seen ended (in order)
        self._held: Counter[str] = Counter()
        self._lock = threading.Lock()

    def claim(self, goal: bytes, client: str) -> Reason | None:
        """Record ``client`` as the sender of a new goal; why not: the id is another's, or the
        client holds its most goals, none of them ended."""
        with self._lock:
            self._forget_old()
            owner = self._owner.get(goal)
            if owner is not None:
                return None if owner == client else Drop.FOREIGN_GOAL
            if self._held[client] >= self.cap:
                oldest = next((g for g in self._ended if self._owner[g] == client), None)
                if oldest is None:
                    return Drop.TOO_MANY_GOALS
                self._drop(oldest)
            self._owner[goal] = client
            self._held[client] += 1
            return None

    def release(self, goal: bytes, client: str) -> None:
        """A goal that was not accepted (or never answered) belongs to nobody."""
        with self._lock:
            if self._owner.get(goal) == client:
                self._drop(goal)

    def owns(self, client: str, goal: bytes) -> bool:
        with self._lock:
            return self._owner.get(goal) == client

    def covered(self, client: str, goal: bytes, stamp: Stamp) -> list[bytes]:
        """The goals of ``client``, not ended, that a cancel of ``goal`` and ``stamp`` covers
        as ROS reads it: no id and no time, every goal; a time, those accepted at or before
        it (as far as their status said); an id, that goal."""
        with self._lock:
            return [g for g, owner in self._owner.items()
                    if owner == client and g not in self._ended
                    and (g == goal or goal == NO_GOAL and stamp == (0, 0)
                         or stamp != (0, 0) and g in self._stamp and self._stamp[g] <= stamp)]

    def update(self, statuses: Iterable[Any]) -> None:
        """What the action server's status (every goal it knows) says: when goals were
        accepted, which have ended, and which it no longer knows (a goal it listed before,
        missing now: ended too). Ended goals are forgotten :attr:`keep` seconds from now."""
        now = self.clock()
        with self._lock:
            listed = set()
            for status in statuses:
                goal = bytes(status.goal_info.goal_id.uuid)
                if goal not in self._owner:
                    continue
                listed.add(goal)
                stamp = status.goal_info.stamp
                self._stamp[goal] = (stamp.sec, stamp.nanosec)
                if status.status in ENDED and goal not in self._ended:
                    self._ended[goal] = now
            for goal in self._stamp.keys() - listed - self._ended.keys():
                self._ended[goal] = now

    def ended(self, goal: bytes) -> None:
        """A goal whose result came: forgotten :attr:`keep` seconds from now."""
        now = self.clock()
        with self._lock:
            if goal in self._owner and goal not in self._ended:
                self._ended[goal] = now

    def _drop(self, goal: bytes) -> None:
        client = self._owner.pop(goal)
        self._stamp.pop(goal, None)
        self._ended.pop(goal, None)
        self._held[client] -= 1
        if not self._held[client]:
            del self._held[client]

    def _forget_old(self) -> None:
        limit = self.clock() - self.keep
        while self._ended:
            goal, when = next(iter(self._ended.items()))
            if when > limit:
                return
            self._drop(goal)


@dataclass
class Answer:
    """A call answered by the serving bridge itself (never served): counted by ``reason``
    when it is one."""

    response: Any
    reason: Reason | None = None
    detail: str = ""


@dataclass
class Split:
    """A call served as several (one cancel per goal), answered with their answers merged
    (``None`` for one that failed)."""

    requests: list[Any]
    merge: Callable[[list[Any]], Any]


class ClientGoals:
    """One part of an action as one client may use it: its calls about goals it did not send
    are answered as the action server answers for a goal it does not know (never served), a
    cancel of many goals reaches only its own, its topics carry only its own goals' feedback
    and status."""

    def __init__(self, goals: Goals, client: str, part: str, interface: Any, raw: bool):
        self.goals, self.client, self.part = goals, client, part
        self.interface = interface  # the part's service (Request/Response) or message class
        self.raw = raw  # messages are serialized CDR (codec cdr)
        self._shown: list[tuple[bytes, int]] | None = None  # the status the client saw last

    # services: send_goal, cancel_goal, get_result
    def screen(self, request: Any) -> Answer | Split | None:
        """How a request is handled: answered here, split, or (None) served as it is."""
        response = self.interface.Response()
        if self.part == "cancel_goal":
            return self._cancel(request, response)
        goal = bytes(request.goal_id.uuid)
        if self.part == "send_goal":
            why = self.goals.claim(goal, self.client)
            if why is None:
                return None
            return Answer(response, why, f"{self.client} sent a goal under another's id" if why
                          is Drop.FOREIGN_GOAL else f"{self.client} has {self.goals.cap} goals")
        if self.goals.owns(self.client, goal):
            return None
        response.status = STATUS_UNKNOWN
        return Answer(response, Drop.FOREIGN_GOAL, f"{self.client} asked for the result of a "
                      "goal not its own")

    def _cancel(self, request: Any, response: Any) -> Answer | Split | None:
        info = request.goal_info
        goal, stamp = bytes(info.goal_id.uuid), (info.stamp.sec, info.stamp.nanosec)
        if goal != NO_GOAL and stamp == (0, 0):  # one goal
            if self.goals.owns(self.client, goal):
                return None
            response.return_code = CANCEL_UNKNOWN_GOAL
            return Answer(response, Drop.FOREIGN_GOAL, f"{self.client} asked to cancel a goal "
                          "not its own")
        mine = self.goals.covered(self.client, goal, stamp)
        if not mine:  # as ROS answers a cancel that covers no goal
            return Answer(response)
        requests = []
        for each in mine:
            one = self.interface.Request()
            one.goal_info.goal_id.uuid = list(each)
            requests.append(one)
        return Split(requests, self._merge)

    def _merge(self, answers: list[Any]) -> Any:
        response = self.interface.Response()
        response.goals_canceling = [info for answer in answers if answer is not None
                                    for info in answer.goals_canceling]
        return response

    def answered(self, request: Any, response: Any | None) -> None:
        """The action server's answer (None: none came): a goal not accepted is nobody's, a
        result says its goal ended."""
        if self.part == "send_goal" and (response is None or not response.accepted):
            self.goals.release(bytes(request.goal_id.uuid), self.client)
        elif self.part == "get_result" and response is not None and response.status in ENDED:
            self.goals.ended(bytes(request.goal_id.uuid))

    # topics: feedback, status
    def select(self, message: Any) -> Any | None:
        """What of ``message`` the client may see: its goals' feedback, the status of its goals
        (an array of the others left out, not sent again when only theirs changed); None:
        nothing."""
        if self.part == "feedback":
            goal = bytes(message[4:20]) if self.raw else bytes(message.goal_id.uuid)
            return message if self.goals.owns(self.client, goal) else None
        from rclpy.serialization import deserialize_message, serialize_message

        array = deserialize_message(bytes(message), self.interface) if self.raw else message
        self.goals.update(array.status_list)
        mine = self.interface(status_list=[s for s in array.status_list if self.goals.owns(
            self.client, bytes(s.goal_info.goal_id.uuid))])
        shown = [(bytes(s.goal_info.goal_id.uuid), s.status) for s in mine.status_list]
        if shown == self._shown:
            return None
        self._shown = shown
        return serialize_message(mine) if self.raw else mine


def client_goals(goals: Goals, client: str, name: str, interface: Any,
                 raw: bool) -> ClientGoals:
    """The part named ``name`` (``<action>/_action/<part>``) as ``client`` may use it."""
    return ClientGoals(goals, client, name.rsplit("/", 1)[1], interface, raw)
