"""A ROS side that serves and calls actions: a node of its own in one DDS domain, for the tests of
actions across the link (the ``action_side`` fixture of conftest.py)."""

from __future__ import annotations

import threading
import time
from typing import Any

from test_msgs.action import Fibonacci, NestedMessage

FEEDBACK_EVERY = 0.05  # seconds between two feedbacks of the test's action server


class ActionSide:
    """A node of its own in one domain, spun by rclpy's multi-threaded executor (an action
    server's execute callback runs while the node serves other calls)."""

    def __init__(self, domain_id: int, name: str):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        self.stopping = threading.Event()  # goals still running end when the side closes
        self.running = 0
        self.ended = threading.Condition()

    def fibonacci_server(self, name: str) -> Any:
        from rclpy.action import ActionServer, CancelResponse

        def execute(goal_handle: Any) -> Any:
            with self.ended:
                self.running += 1
            try:
                return work(goal_handle)
            finally:
                with self.ended:
                    self.running -= 1
                    self.ended.notify_all()

        def work(goal_handle: Any) -> Any:
            feedback = Fibonacci.Feedback(sequence=[0, 1])
            for _ in range(goal_handle.request.order):
                if self.stopping.is_set():
                    goal_handle.abort()
                    return Fibonacci.Result()
                if goal_handle.is_cancel_requested:
                    goal_handle.canceled()
                    return Fibonacci.Result(sequence=feedback.sequence)
                feedback.sequence.append(feedback.sequence[-1] + feedback.sequence[-2])
                goal_handle.publish_feedback(feedback)
                time.sleep(FEEDBACK_EVERY)  # the action's work: it takes a while
            goal_handle.succeed()
            return Fibonacci.Result(sequence=feedback.sequence)

        return ActionServer(self.node, Fibonacci, name, execute,
                            cancel_callback=lambda _: CancelResponse.ACCEPT)

    def nested_server(self, name: str) -> Any:
        from rclpy.action import ActionServer

        def execute(goal_handle: Any) -> Any:
            goal = goal_handle.request
            goal_handle.publish_feedback(NestedMessage.Feedback(
                nested_field=goal.nested_field, nested_field_no_pkg=goal.nested_field_no_pkg,
                nested_different_pkg=goal.nested_different_pkg))
            goal_handle.succeed()
            return NestedMessage.Result(
                nested_field=goal.nested_field, nested_field_no_pkg=goal.nested_field_no_pkg,
                nested_different_pkg=goal.nested_different_pkg)

        return ActionServer(self.node, NestedMessage, name, execute)

    def client(self, action_type: type, name: str) -> Any:
        from rclpy.action import ActionClient

        return ActionClient(self.node, action_type, name)

    def close(self) -> None:
        self.stopping.set()
        with self.ended:  # the goals end before their node
            self.ended.wait_for(lambda: self.running == 0, 5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()
