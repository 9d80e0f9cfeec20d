"""Actions across the link (docs/actions.md): a ROS 2 action *is* three services and two
topics under ``<name>/_action/``, so an ``actions:`` entry becomes those five entries, with the
types rosidl makes for it, and the service and topic routes carry them. ``get_result`` waits as
long as a goal runs (up to an hour); in peer role feedback and status take ``port + 1``.
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

