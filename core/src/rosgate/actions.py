"""Actions across the link (docs/actions.md): a ROS 2 action *is* three services and two
topics under ``<name>/_action/``, so an ``actions:`` entry becomes those five entries, with the
types rosidl makes for it, and the service and topic routes carry them. ``get_result`` waits as
long as a goal runs (up to an hour); in peer role feedback and status take ``port + 1``.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
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
CANCEL_REJECTED = 1
CANCEL_UNKNOWN_GOAL = 2
#: seconds an ended goal is remembered: rclpy's action server keeps a result 900 s by default
KEEP_ENDED = 900.0
#: goals of one action the server remembers per client; past it, a new goal is not accepted
GOALS_PER_CLIENT = 1000
_NO_GOAL = bytes(16)


class Goals:
    """Who sent each goal of one action a server serves to its clients: goal id -> client.
    Ended goals are forgotten :data:`KEEP_ENDED` seconds later, and a client holds at most
    :data:`GOALS_PER_CLIENT` (its oldest ended goal goes first)."""

    def __init__(self, keep: float = KEEP_ENDED, cap: int = GOALS_PER_CLIENT,
                 clock: Callable[[], float] = time.monotonic):
        self.keep, self.cap, self.clock = keep, cap, clock
        self._owner: dict[bytes, str] = {}
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

    def ended(self, goals: Iterable[bytes]) -> None:
        """Goals the action server says have ended: forgotten :attr:`keep` seconds from now."""
        now = self.clock()
        with self._lock:
            for goal in goals:
                if goal in self._owner and goal not in self._ended:
                    self._ended[goal] = now

    def _drop(self, goal: bytes) -> None:
        client = self._owner.pop(goal)
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


class ClientGoals:
    """One part of an action as one client may use it: its calls about goals it did not send
    are answered as the action server answers for a goal it does not know (never served), its
    topics carry only its own goals' feedback and status."""

    def __init__(self, goals: Goals, client: str, part: str, interface: Any, raw: bool):
        self.goals, self.client, self.part = goals, client, part
        self.interface = interface  # the part's service (Request/Response) or message class
        self.raw = raw  # messages are serialized CDR (codec cdr)

    # services: send_goal, cancel_goal, get_result
    def refuse(self, request: Any) -> tuple[Reason, str, Any] | None:
        """Why a request is answered without being served (reason, detail, the answer), or
        None: serve it."""
        response = self.interface.Response()
        if self.part == "send_goal":
            why = self.goals.claim(bytes(request.goal_id.uuid), self.client)
            if why is None:
                return None
            return why, (f"{self.client} sent a goal under another's id" if why is
                         Drop.FOREIGN_GOAL else f"{self.client} has {self.goals.cap} goals "
                         "running"), response
        if self.part == "cancel_goal":
            info = request.goal_info
            goal = bytes(info.goal_id.uuid)
            if goal == _NO_GOAL or info.stamp.sec or info.stamp.nanosec:
                response.return_code = CANCEL_REJECTED
                return (Drop.FOREIGN_GOAL, f"{self.client} asked to cancel every goal (or those "
                        "before a time), which may be other clients'", response)
            if self.goals.owns(self.client, goal):
                return None
            response.return_code = CANCEL_UNKNOWN_GOAL
            return Drop.FOREIGN_GOAL, f"{self.client} asked to cancel a goal not its own", response
        goal = bytes(request.goal_id.uuid)
        if self.goals.owns(self.client, goal):
            return None
        response.status = STATUS_UNKNOWN
        return Drop.FOREIGN_GOAL, f"{self.client} asked for a result of a goal not its own", \
            response

    def answered(self, request: Any, response: Any | None) -> None:
        """The action server's answer (None: none came): a goal not accepted is nobody's, a
        result says its goal ended."""
        if self.part == "send_goal" and (response is None or not response.accepted):
            self.goals.release(bytes(request.goal_id.uuid), self.client)
        elif self.part == "get_result" and response is not None and response.status in ENDED:
            self.goals.ended([bytes(request.goal_id.uuid)])

    # topics: feedback, status
    def select(self, message: Any) -> Any | None:
        """What of ``message`` the client may see: its goals' feedback, the status of its goals
        (an array of the others left out); None: nothing."""
        if self.part == "feedback":
            goal = bytes(message[4:20]) if self.raw else bytes(message.goal_id.uuid)
            return message if self.goals.owns(self.client, goal) else None
        from rclpy.serialization import deserialize_message, serialize_message

        array = deserialize_message(bytes(message), self.interface) if self.raw else message
        self.goals.ended(bytes(s.goal_info.goal_id.uuid) for s in array.status_list
                         if s.status in ENDED)
        mine = self.interface(status_list=[s for s in array.status_list if self.goals.owns(
            self.client, bytes(s.goal_info.goal_id.uuid))])
        return serialize_message(mine) if self.raw else mine


def client_goals(goals: Goals, client: str, name: str, interface: Any,
                 raw: bool) -> ClientGoals:
    """The part named ``name`` (``<action>/_action/<part>``) as ``client`` may use it."""
    return ClientGoals(goals, client, name.rsplit("/", 1)[1], interface, raw)
