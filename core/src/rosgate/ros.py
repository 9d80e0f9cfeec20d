"""The ROS side: one rclpy context + node per engine (so several engines, each in its own DDS
domain when asked, live in one process), what its graph shows, and the check of raw CDR from
the network. Types by name, their hashes and QoS words: :mod:`rosgate.rostypes`."""

from __future__ import annotations

import ctypes
import functools
import logging
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from .batch import Batches
from .errors import CodecError
from .rostypes import QOS_FOUND_DEPTH, QOS_FOUND_MAX_DEPTH, capsule_pointer

if TYPE_CHECKING:
    from rclpy.node import Node

_log = logging.getLogger("rosgate")


def cdr_checker(msg_type: type) -> Callable[[bytes], None]:
    """A check that serialized CDR bytes are a valid ``msg_type`` (else :class:`CodecError`), so
    bytes from an unknown sender never reach a subscriber as a message it cannot read.

    The middleware's deserializer (``rmw_deserialize`` through ctypes: ~2 us for a 2.5 kB String
    in a tight loop, ~15 us cold in a bridge) beats rclpy's ``deserialize_message`` (the
    fallback: ~6-16 us, ~1.7 ms for a 1 MiB Image); in front of either, the quick look of
    :mod:`rosgate.cdr` passes what is certainly well-formed."""
    checker = _RmwChecker.make(msg_type)
    full: Callable[[bytes], None]
    if checker is not None:
        full = checker.check
    else:
        from rclpy.serialization import deserialize_message

        def full(data: bytes) -> None:
            try:
                deserialize_message(data, msg_type)
            except Exception as exc:  # rclpy raises RMWError; any failure means unreadable
                raise CodecError(f"not a valid {msg_type.__name__}: {exc}") from None

    from .cdr import walker

    quick = walker(msg_type)
    if quick is None:
        return full

    def check(data: bytes) -> None:
        if not quick(data):
            full(data)

    return check


class _SerializedMessage(ctypes.Structure):  # rmw_serialized_message_t; the allocator unused
    _fields_ = [("buffer", ctypes.c_char_p), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", ctypes.c_void_p * 5)]


class _RmwChecker:
    """``rmw_deserialize`` into a C message of one type, reused (under a lock: frames of one
    topic may come from several links at once). Deserializing into a used message is what the
    generated type support does anyway: it finalizes strings and sequences before filling them."""

    def __init__(self, msg_type: type, rmw: Any, reset_error: Any):
        meta: Any = type(msg_type)  # rosidl's metaclass holds the C type support
        meta.__import_type_support__()
        self.name = msg_type.__name__
        self.type_support = capsule_pointer(meta._TYPE_SUPPORT, None)
        create = ctypes.CFUNCTYPE(ctypes.c_void_p)(
            capsule_pointer(meta._CREATE_ROS_MESSAGE, None))
        self._destroy = ctypes.CFUNCTYPE(None, ctypes.c_void_p)(
            capsule_pointer(meta._DESTROY_ROS_MESSAGE, None))
        self.message = create()
        if not self.message:
            raise MemoryError(f"cannot create a {self.name}")
        self.serialized = _SerializedMessage()
        self.address = ctypes.addressof(self.serialized)
        pointer = ctypes.c_void_p
        self.deserialize = ctypes.CFUNCTYPE(ctypes.c_int, pointer, pointer, pointer)(
            ("rmw_deserialize", rmw))
        self.reset_error = reset_error
        self.lock = threading.Lock()

    @classmethod
    def make(cls, msg_type: type) -> _RmwChecker | None:
        """A checker, or None where the middleware's library or the type's C support is not
        found (then rclpy's deserializer does the check)."""
        library = _find_rmw()
        if library is None:
            return None
        try:
            return cls(msg_type, *library)
        except (AttributeError, OSError, MemoryError) as exc:
            _log.debug("CDR check of %s through rclpy: %s", msg_type.__name__, exc)
            return None

    def check(self, data: bytes | bytearray) -> None:
        serialized = self.serialized
        with self.lock:
            # a reassembled frame (bytearray): its buffer, exported for the call only
            view = None if type(data) is bytes else (ctypes.c_char * len(data)).from_buffer(data)
            serialized.buffer = data if view is None else ctypes.cast(view, ctypes.c_char_p)
            serialized.buffer_length = serialized.buffer_capacity = len(data)
            failed = self.deserialize(self.address, self.type_support, self.message)
            serialized.buffer = None  # do not keep the frame alive
            del view
        if failed:
            self.reset_error()  # else rcutils complains to stderr about the next error
            raise CodecError(f"not a valid {self.name} (its CDR does not deserialize)")

    def __del__(self) -> None:
        if self.message:
            self._destroy(self.message)
            self.message = None


@functools.cache
def _find_rmw() -> tuple[Any, Any] | None:
    """The library with ``rmw_deserialize``, and ``rcutils_reset_error``, among those rclpy loaded:
    ``librmw_implementation`` (ROS from apt: it dispatches to the middleware in use) or else the
    one middleware library linked in (the wheels from the package index)."""
    import rclpy.serialization  # noqa: F401  (loads the middleware)

    try:
        with open("/proc/self/maps") as maps:
            loaded = {line.split()[-1] for line in maps if ".so" in line}
    except OSError:
        return None
    rmw = reset = None
    for path in sorted(loaded, key=lambda path: "librmw_implementation." not in path):
        name = path.rsplit("/", 1)[-1]
        try:
            if rmw is None and name.startswith("librmw_") and "dds_common" not in name:
                library = ctypes.CDLL(path)
                rmw = library if hasattr(library, "rmw_deserialize") else None
            if reset is None and name.startswith("librcutils."):
                reset = ctypes.CDLL(path).rcutils_reset_error
        except OSError:
            continue
    if rmw is None or reset is None:
        return None
    reset.restype, reset.argtypes = None, []
    return rmw, reset


class _Deferred:
    """What a deferred service's callback returns: the answer comes later (see deferred_service)."""

    __slots__ = ("request",)

    def __init__(self, request: Any, response: Any = None):
        self.request = request


SPIN = 0.1  # seconds the executor spins before the spinning thread checks for a stop
#: seconds after a node is made in which its graph may still lack what is there (DDS finds the
#: other participants with a few quick announcements, then every few seconds)
DISCOVERY = 5.0


class _Spinner:
    """An EventsExecutor with one node, spun in a background thread, and the batch windows of
    the node's subscriptions (closed on that thread)."""

    def __init__(self, context: Any, node: Any, name: str):
        from rclpy.experimental import EventsExecutor

        self.context = context
        self.executor = EventsExecutor(context=context)
        self.executor.add_node(node)
        self.batches = Batches()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=name, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        # spin_once, not EventsExecutor.spin(): while that runs, creating a subscription from
        # another thread hangs (rclpy from the package index). Context.ok is asked every SPIN
        # seconds, not per message (it takes a lock: 3-4 us/msg at 8,000 msg/s). While a batch
        # window is open (rosgate.batch) the thread sleeps until it closes.
        stop, ok, clock, batches = self._stop, self.context.ok, time.monotonic, self.batches
        spin_once = self.executor.spin_once
        checked = clock()
        while not stop.is_set():
            if batches:
                wait = batches.close_due(clock())
                if wait is not None:
                    time.sleep(wait)
                    continue
            spin_once(timeout_sec=SPIN)
            now = clock()
            if now - checked >= SPIN:
                if not ok():
                    return
                checked = now

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.executor.shutdown()


class RosNode:
    """A node in a context of its own, spun in a background thread.

    The subscriptions of ``real_time`` topics belong to a second node in the same context (the
    same DDS participant), made with the first of them and spun by an executor and a thread of
    its own: one executor serves its subscriptions in the order their messages came, so a
    Twist would wait behind every message of a flooded topic that came before it (and a
    shallow history would overwrite it meanwhile)."""

    def __init__(self, name: str, domain_id: int | None = None, namespace: str | None = None):
        import rclpy
        from rclpy.context import Context

        self.context = Context()
        self.born = time.monotonic()
        self._name, self._namespace = re.sub(r"[^A-Za-z0-9_]", "_", f"rosgate_{name}"), namespace
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = self._new_node(self._name)
        self._spinner = _Spinner(self.context, self.node, f"ros-{name}")
        #: the batch windows of its subscriptions, closed on the executor's thread
        self.batches = self._spinner.batches
        #: the real_time topics' node and its spinner, once one subscribes
        self._urgent: tuple[Node, _Spinner] | None = None
        self._urgent_lock = threading.Lock()

    def _new_node(self, name: str) -> Node:
        import rclpy

        return rclpy.create_node(name, context=self.context, start_parameter_services=False,
                                 namespace=self._namespace)

    def _urgent_node(self) -> tuple[Node, _Spinner]:
        with self._urgent_lock:
            if self._urgent is None:
                node = self._new_node(f"{self._name}_real_time")
                self._urgent = node, _Spinner(self.context, node, f"ros-{self._name}-real-time")
            return self._urgent

    def batches_of(self, real_time: bool) -> Batches:
        """Where the batch windows of a subscription (of a ``real_time`` topic or not) open."""
        return self._urgent_node()[1].batches if real_time else self.batches

    def subscribe(self, msg_type: type, topic: str, qos: Any, callback: Callable[[Any], None],
                  raw: bool, real_time: bool = False) -> Any:
        """A subscription; a ``real_time`` topic's is served on a thread of its own."""
        node = self._urgent_node()[0] if real_time else self.node
        return node.create_subscription(msg_type, topic, callback, qos, raw=raw)

    @staticmethod
    def taker(subscription: Any) -> Callable[[], tuple[Any, int] | None]:
        """For a subscription's callback (on the executor's thread): the next message waiting in
        the middleware and its reception stamp (``time.time_ns()``), or None, without waiting;
        a callback takes a backlog in one go. (This rclpy's EventsExecutor fails on callbacks
        that ask for the message info, so the stamp is taken here.)"""
        take = subscription.handle.take_message
        msg_type, raw = subscription.msg_type, subscription.raw

        def next_waiting() -> tuple[Any, int] | None:
            got = take(msg_type, raw)
            return None if got is None else (got[0], got[1]["received_timestamp"])

        return next_waiting

    def qos_found(self, topic: str) -> dict[str, Any] | None:
        """The QoS ``topic``'s publishers on the graph (not this node's) agree on, as ROS's
        best-available QoS decides: reliable, transient_local when all are, deep enough for all
        their histories; None without publishers."""
        from rclpy import qos

        profiles = self.publishers_of(topic)
        if not profiles:
            return None
        reliable = all(p.reliability == qos.ReliabilityPolicy.RELIABLE for p in profiles)
        latched = all(p.durability == qos.DurabilityPolicy.TRANSIENT_LOCAL for p in profiles)
        depth = sum(max(1, p.depth) for p in profiles) if latched else QOS_FOUND_DEPTH
        return {"reliability": "reliable" if reliable else "best_effort",
                "durability": "transient_local" if latched else "volatile",
                "depth": max(QOS_FOUND_DEPTH, min(depth, QOS_FOUND_MAX_DEPTH))}

    def published(self, topic: str) -> bool:
        """Whether the graph shows a publisher of ``topic`` (this node's too): a cheap look."""
        return self.node.count_publishers(topic) > 0

    def publishers_of(self, topic: str) -> list[Any]:
        """The QoS profiles of ``topic``'s publishers on the graph, not this node's."""
        if not self.published(topic):
            return []
        me = (self.node.get_name(), self.node.get_namespace())
        return [info.qos_profile for info in self.node.get_publishers_info_by_topic(topic)
                if (info.node_name, info.node_namespace) != me]

    def matched_all(self, publisher: Any) -> bool | None:
        """Whether ``publisher`` has matched every subscription the graph shows on its topic
        that its reliability and durability can match; None when the graph shows none and this
        node is past its first :data:`DISCOVERY` seconds (nobody waits for it). Not rclpy's
        ``qos_check_compatible``: it takes the graph's infinite deadline for a finite one."""
        from rclpy import qos

        mine = publisher.qos_profile
        weaker = {(qos.ReliabilityPolicy.RELIABLE, qos.ReliabilityPolicy.BEST_EFFORT),
                  (qos.DurabilityPolicy.TRANSIENT_LOCAL, qos.DurabilityPolicy.VOLATILE)}
        expected = sum((info.qos_profile.reliability, mine.reliability) not in weaker
                       and (info.qos_profile.durability, mine.durability) not in weaker
                       for info in self.node.get_subscriptions_info_by_topic(publisher.topic_name))
        if not expected:
            return None if time.monotonic() - self.born > DISCOVERY else False
        return expected <= publisher.get_subscription_count()

    @staticmethod
    def acknowledged(publisher: Any, timeout: float) -> bool:
        """Wait (at most ``timeout`` s) until ``publisher``'s subscribers acknowledged all it
        published (reliable ones: a best-effort subscriber acknowledges nothing)."""
        from rclpy.duration import Duration

        return bool(publisher.wait_for_all_acked(Duration(nanoseconds=int(timeout * 1e9))))

    @staticmethod
    def unacknowledged_at_most(profile: Any) -> int:
        """How many messages a publisher of ``profile`` can hold that its subscribers have not
        acknowledged: its depth when reliable and keep-last; 0 when it holds none (best
        effort) or has no bound (keep-all)."""
        from rclpy import qos

        return (profile.depth if profile.reliability == qos.ReliabilityPolicy.RELIABLE
                and profile.history == qos.HistoryPolicy.KEEP_LAST else 0)

    def publisher(self, msg_type: type, topic: str, qos: Any) -> Any:
        return self.node.create_publisher(msg_type, topic, qos)

    def served(self, names: Iterable[str]) -> set[str]:
        """Which of the services ``names`` have a server on the graph that is not a node of this
        node's namespace (rosgate's own: a bridge's proxy is never taken for a real server). One
        count per name; the nodes of that namespace are asked only when a name has servers."""
        counts = {name: self.node.count_services(name) for name in names}
        if not any(counts.values()):
            return set()
        mine: Counter[str] = Counter()
        here = self.node.get_namespace()
        for node, namespace in set(self.node.get_node_names_and_namespaces()):
            if namespace != here:
                continue
            try:
                services = self.node.get_service_names_and_types_by_node(node, namespace)
            except Exception:  # the node went between the two questions: it serves nothing now
                continue
            mine.update(name for name, _ in services if name in counts)
        return {name for name, count in counts.items() if count > mine[name]}

    @staticmethod
    def raw_publisher(publisher: Any) -> Callable[[bytes | bytearray], None]:
        """Publish serialized CDR through ``publisher``: ``bytes`` or a ``bytearray`` (a
        reassembled frame, handed over without a copy; ``Publisher.publish`` takes bytes only)."""
        handle = publisher.handle
        publish_raw = handle.publish_raw

        def publish(data: bytes | bytearray) -> None:
            with handle:  # as Publisher.publish: the publisher is not destroyed meanwhile
                publish_raw(data)

        return publish

    def deferred_service(self, srv_type: type, name: str, qos: Any,
                         on_request: Callable[[Any, Callable[[Any], None]], None]) -> Any:
        """A service server whose answers may come later: ``on_request(request, respond)`` runs
        on the executor thread and must not block; ``respond(response)``, once, from any thread.

        Not an async callback: EventsExecutor hands the coroutine itself to ``send_response``
        and rclpy's Python executors poll awaiting tasks in a busy loop. So the callback returns
        a marker, and this instance's ``send_response`` turns it into the call of ``on_request``.
        """
        from rclpy.exceptions import InvalidHandle
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        from rclpy.service import Service

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
        elif not self.node.destroy_subscription(entity) and self._urgent is not None:
            self._urgent[0].destroy_subscription(entity)

    def close(self) -> None:
        spun = [(self.node, self._spinner)]
        with self._urgent_lock:
            spun += [self._urgent] if self._urgent is not None else []
            self._urgent = None
        for node, spinner in spun:
            spinner.close()
            node.destroy_node()
        self.context.try_shutdown()
