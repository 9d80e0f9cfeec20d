"""Actions across the link. A ROS 2 action *is* three services and two topics, under
``<name>/_action/``: ``send_goal`` (a goal, answered accepted or not), ``cancel_goal``,
``get_result`` (answered when the goal ends), ``feedback`` and ``status`` (published by the
action server). An ``actions:`` entry becomes those five entries, with the types rosidl makes
for the action (``pkg/action/Type_SendGoal``, ``Type_GetResult``, ``Type_FeedbackMessage``,
``action_msgs/srv/CancelGoal``, ``action_msgs/msg/GoalStatusArray``), and the service and topic
routes carry them: the ROS action client on the calling side and the ROS action server on the
serving side talk as if they were on one graph.

* ``direction: transmit``: goals sent here are served on the far side: the three services are
  transmitted, feedback and status received; ``receive`` the other way round.
* ``send_goal`` and ``cancel_goal`` are answered within the entry's ``timeout``: a goal for an
  action nobody serves is answered "not accepted", a cancel the bridge cannot deliver
  "rejected". ``get_result`` waits as long as the goal runs (up to an hour); when it cannot be
  answered (the link or the session is lost) it answers status ABORTED.
* status is ``transient_local`` (as ROS publishes it), feedback reliable, depth 10.
* In peer role an action takes two ports: ``port`` for its calls (on the serving side) and
  ``port + 1`` for its feedback and status (on the calling side).
"""

from __future__ import annotations

from .config import TIMEOUT_MAX, ActionConfig, ServiceConfig, TopicConfig

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

