"""The ROS side: message types, QoS, and one rclpy context + node per engine.

Each engine gets its own rclpy ``Context`` (and DDS domain when asked), so several engines can
live in one process. The node is spun by ``rclpy.experimental.EventsExecutor`` in a thread of
its own, with a loop of ``spin_once`` (its ``spin()`` was seen to deliver nothing and to hang at
shutdown with the rclpy from the package index).
"""

from __future__ import annotations

import importlib
import logging
import re
import threading
from typing import Any, Callable

from .errors import CodecError

_log = logging.getLogger("rosgate")

TYPE_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv)/([A-Z][A-Za-z0-9]*)$")


class TypeNotFound(LookupError):
    """An interface that is not installed; the message says which package to install."""


def resolve_type(name: str) -> type:
    """``pkg/msg/Type`` (or ``pkg/srv/Type``) to its Python class.

    Names come from peers too, so nothing is imported before ``pkg`` is known to be a ROS
    interface package (:func:`is_interface_package`): ``this/msg/Foo`` must not import ``this``."""
    match = TYPE_NAME.match(name)
    if not match:
        raise TypeNotFound(f"{name!r} is not an interface name of the form pkg/msg/Type")
    package, kind, type_name = match.groups()
    dist = "ros-jazzy-" + package.replace("_", "-")
    missing = TypeNotFound(
        f"interface package {package!r} is not installed (apt install ros-$ROS_DISTRO-"
        f"{package.replace('_', '-')}, or pip install {dist})")
    if not is_interface_package(package, kind):
        raise missing
    try:
        module = importlib.import_module(f"{package}.{kind}")
    except ImportError:
        raise missing from None
    cls = getattr(module, type_name, None)
    if not isinstance(cls, type):
        known = sorted(n for n in dir(module) if n[:1].isupper() and not n.startswith("Metaclass"))
        raise TypeNotFound(f"package {package!r} has no {kind} {type_name!r} "
                           f"(it has: {', '.join(known)})")
    return cls


def is_interface_package(package: str, kind: str) -> bool:
    """Whether ``package`` is an installed ROS interface package with ``kind`` (msg, srv)
    interfaces — decided without importing it: the ament resource index lists it, or its
    folder holds the C type support rosidl generates and a ``kind`` subpackage."""
    import importlib.util
    import os
    import sys
    from pathlib import Path

    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    listed = any((Path(prefix) / "share" / "ament_index" / "resource_index" / "rosidl_interfaces"
                  / package).is_file() for prefix in prefixes)
    try:
        spec = importlib.util.find_spec(package)  # a top-level name: finds, does not import
    except (ImportError, ValueError):
        return False
    if spec is None or not spec.submodule_search_locations:
        return False
    for location in spec.submodule_search_locations:
        folder = Path(location)
        generated = any(folder.glob(f"{package}_s__rosidl_typesupport_c*"))
        if (folder / kind / "__init__.py").is_file() and (listed or generated):
            return True
    return False


def qos_profile(spec: int | str | dict) -> Any:
    """A QoS profile from a depth, a profile name or a mapping (already validated by config)."""
    from rclpy import qos

    if isinstance(spec, int):
        return qos.QoSProfile(depth=spec)
    if isinstance(spec, str):  # a name config.QOS_PROFILES admits
        return getattr(qos, f"qos_profile_{spec}")
    profile = qos.QoSProfile(depth=spec.get("depth", 10))
    if "reliability" in spec:
        profile.reliability = getattr(qos.ReliabilityPolicy, spec["reliability"].upper())
    if "durability" in spec:
        profile.durability = getattr(qos.DurabilityPolicy, spec["durability"].upper())
    if "history" in spec:
        profile.history = getattr(qos.HistoryPolicy, spec["history"].upper())
    return profile


def is_reliable(spec: int | str | dict) -> bool:
    """Whether a topic's frames wait out a link loss: unless its QoS says best effort (the
    system default and best-available profiles are reliable with every shipped RMW)."""
    from rclpy import qos

    return qos_profile(spec).reliability != qos.ReliabilityPolicy.BEST_EFFORT


def cdr_checker(msg_type: type) -> Callable[[bytes], None]:
    """A check that serialized CDR bytes are a valid ``msg_type``: deserializing once, in C
    (~4 us for a 2.5 kB String), so bytes from an unknown sender never reach a ROS subscriber as
    a message it cannot read. Raises :class:`rosgate.CodecError` saying why."""
    from rclpy.serialization import deserialize_message

    def check(data: bytes) -> None:
        try:
            deserialize_message(data, msg_type)
        except Exception as exc:  # rclpy raises RMWError; any failure means unreadable
            raise CodecError(f"not a valid {msg_type.__name__}: {exc}") from None

    return check


class _Deferred:
    """What a deferred service's callback returns: the answer comes later (see deferred_service)."""

    __slots__ = ("request",)

    def __init__(self, request: Any, response: Any = None):
        self.request = request


class RosNode:
    """A node in a context of its own, spun in a background thread."""

    def __init__(self, name: str, domain_id: int | None = None):
        import rclpy
        from rclpy.context import Context
        from rclpy.experimental import EventsExecutor

        self._rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        node_name = re.sub(r"[^A-Za-z0-9_]", "_", f"rosgate_{name}")
        self.node = rclpy.create_node(node_name, context=self.context,
                                      start_parameter_services=False)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"ros-{name}", daemon=True)
        self._thread.start()

    @property
    def logger(self) -> Any:
        return self.node.get_logger()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def subscribe(self, msg_type: type, topic: str, qos: Any, callback: Callable[[Any], None],
                  raw: bool) -> Any:
        return self.node.create_subscription(msg_type, topic, callback, qos, raw=raw)

    def publisher(self, msg_type: type, topic: str, qos: Any) -> Any:
        return self.node.create_publisher(msg_type, topic, qos)

    def deferred_service(self, srv_type: type, name: str, qos: Any,
                         on_request: Callable[[Any, Callable[[Any], None]], None]) -> Any:
        """A service server whose answers may come later, from any thread.

        ``on_request(request, respond)`` runs on the executor thread and must not block; calling
        ``respond(response)`` (once, from any thread) answers the caller. Why not an async
        callback: EventsExecutor does not run coroutines (it hands the coroutine itself to
        ``send_response``: TypeError), and rclpy's Python executors resume awaiting tasks by
        polling them in a busy loop. Both executors answer by calling ``service.send_response
        (result, header)`` on the service object, so the callback returns a marker and
        ``send_response`` is replaced on this instance: given the marker it passes the request
        and a ``respond`` bound to the request's header to ``on_request``.
        """
        from rclpy.service import Service

        from rclpy.exceptions import InvalidHandle
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        service = self.node.create_service(srv_type, name, _Deferred, qos_profile=qos)

        def respond(response: Any, header: Any) -> None:
            try:
                Service.send_response(service, response, header)
            except InvalidHandle:  # the service was destroyed (a client left) while it waited
                pass
            except (_rclpy.RCLError, _rclpy.RMWError) as exc:
                # Fast DDS drops an answer to a caller whose reader it has not discovered yet
                # ("client will not receive response"): the caller's own timeout covers it
                _log.warning("%s: an answer was lost in ROS: %s", name, str(exc).splitlines()[0])

        def send_response(result: Any, header: Any) -> None:
            if isinstance(result, _Deferred):
                on_request(result.request, lambda response: respond(response, header))
            else:
                respond(result, header)

        # replacing a method on this instance is the point (see above); mypy forbids it in general
        service.send_response = send_response  # type: ignore[method-assign,assignment]
        return service

    def client(self, srv_type: type, name: str, qos: Any) -> Any:
        return self.node.create_client(srv_type, name, qos_profile=qos)

    def destroy(self, entity: Any) -> None:
        from rclpy.client import Client
        from rclpy.service import Service

        if isinstance(entity, Service):
            self.node.destroy_service(entity)
        elif isinstance(entity, Client):
            self.node.destroy_client(entity)
        elif hasattr(entity, "publish"):
            self.node.destroy_publisher(entity)
        else:
            self.node.destroy_subscription(entity)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()
