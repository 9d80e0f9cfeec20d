"""ROS's vocabulary, without a node: interface classes found by name (and the sentence that
says which package to install when one is missing), their RIHS01 type hashes, and the QoS
profiles a file's words name. Asked while routes are made, never per message."""

from __future__ import annotations

import ctypes
import functools
import importlib
import importlib.util
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any

from .options import did_you_mean

_log = logging.getLogger("rosgate")

TYPE_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Z][A-Za-z0-9_]*)$")
#: an action's parts as the graph names them (pkg/action/Type_SendGoal), and in Type.Impl
_ACTION_PARTS = {"SendGoal": "SendGoalService", "GetResult": "GetResultService",
                 "FeedbackMessage": "FeedbackMessage"}


class TypeNotFound(LookupError):
    """An interface that is not installed; the message says which package to install."""


def resolve_type(name: str) -> type:
    """``pkg/msg/Type`` (or ``pkg/srv/Type``) to its Python class. Names come from peers too:
    nothing is imported before ``pkg`` is known to be an interface package (``this/msg/Foo`` must
    not import ``this``)."""
    match = TYPE_NAME.match(name)
    if not match:
        raise TypeNotFound(f"{name!r} is not an interface name of the form pkg/msg/Type")
    package, kind, type_name = match.groups()
    dashed = package.replace("_", "-")
    # one letter off an installed package (std_msg): a typo, not a package to install
    close, hint = did_you_mean(package, interface_packages(), cutoff=0.85)
    missing = TypeNotFound(f"interface package {package!r} is not installed{hint}" + (
        "" if close else f" (apt install ros-$ROS_DISTRO-{dashed}, or pip install "
        f"ros-jazzy-{dashed})"))
    if not is_interface_package(package, kind):
        raise missing
    try:
        module = importlib.import_module(f"{package}.{kind}")
    except ImportError:
        raise missing from None
    cls = getattr(module, type_name, None)
    if cls is None and kind == "action" and "_" in type_name:  # not all exported: in Type.Impl
        base, _, part = type_name.partition("_")
        impl = getattr(getattr(module, base, None), "Impl", None)
        cls = getattr(impl, _ACTION_PARTS.get(part, ""), None)
    if not isinstance(cls, type):
        known = sorted(n for n in dir(module) if n[:1].isupper() and not n.startswith("Metaclass"))
        hint = did_you_mean(type_name, known)[1]
        raise TypeNotFound(f"package {package!r} has no {kind} {type_name!r}{hint} "
                           f"(it has: {', '.join(known)})")
    return cls


def interface_packages() -> list[str]:
    """The ROS interface packages installed here, as the ament resource index lists them (this
    Python's prefix and AMENT_PREFIX_PATH's): what a misspelt package name is compared with."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    found: set[str] = set()
    for prefix in [*prefixes, sys.prefix]:
        index = Path(prefix) / "share" / "ament_index" / "resource_index" / "rosidl_interfaces"
        if index.is_dir():
            found.update(entry.name for entry in index.iterdir())
    return sorted(found)


def is_interface_package(package: str, kind: str) -> bool:
    """Whether ``package`` is an installed ROS interface package with ``kind`` (msg, srv)
    interfaces — decided without importing it: the ament resource index lists it, or its
    folder holds the C type support rosidl generates and a ``kind`` subpackage."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    listed = any((Path(prefix) / "share" / "ament_index" / "resource_index" / "rosidl_interfaces"
                  / package).is_file() for prefix in prefixes)
    try:
        spec = importlib.util.find_spec(package)  # a top-level name: finds, does not import
    except (ImportError, ValueError):
        return False
    folders = (spec.submodule_search_locations or []) if spec else []
    return any((Path(f) / kind / "__init__.py").is_file()
               and (listed or any(Path(f).glob(f"{package}_s__rosidl_typesupport_c*")))
               for f in folders)


class _TypeHash(ctypes.Structure):  # rosidl_type_hash_t: SHA-256 of the type's description
    _fields_ = [("version", ctypes.c_uint8), ("value", ctypes.c_uint8 * 32)]


_GetTypeHash = ctypes.CFUNCTYPE(ctypes.POINTER(_TypeHash), ctypes.c_void_p)


#: the pointer in a PyCapsule: rosidl's metaclasses hold their C functions in capsules
capsule_pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi))


@functools.lru_cache(maxsize=1024)
def type_hash(interface: type) -> str | None:
    """The RIHS01 hash ROS gives ``interface`` (a message or a service class), as the graph
    shows it (``RIHS01_<64 hex digits>``), read from its C type support; None where this ROS
    has none (before Iron) or the type support cannot be read."""
    meta: Any = type(interface)
    try:
        meta.__import_type_support__()
        address = capsule_pointer(meta._TYPE_SUPPORT, None)
        # rosidl_{message,service}_type_support_t (Iron and later) start with pointers only: the
        # hash getter after identifier, data, func (a service's: request, response, event and
        # the event's create and destroy functions too)
        slot = 8 if hasattr(interface, "Request") else 3
        getter = (ctypes.c_void_p * (slot + 1)).from_address(address)[slot]
        if not getter:
            return None
        found = _GetTypeHash(getter)(address)
        if not found or found.contents.version < 1:
            return None
        return f"RIHS{found.contents.version:02}_{bytes(found.contents.value).hex()}"
    except (AttributeError, ValueError, OSError, TypeError) as exc:
        _log.debug("no type hash for %s: %s", getattr(interface, "__name__", interface), exc)
        return None


#: the depth of a QoS found from publishers, and at most what a latched topic's keeps
QOS_FOUND_DEPTH = 10
QOS_FOUND_MAX_DEPTH = 1000
#: an entry without qos before any publisher is found: the default profile, QoSProfile(depth=10)
QOS_UNFOUND = {"reliability": "reliable", "durability": "volatile", "depth": QOS_FOUND_DEPTH}


#: the profiles a file may name (config.QOS_PROFILES) whose reliability is best effort in rclpy
BEST_EFFORT_PROFILES = frozenset({"sensor_data"})


def qos_profile(spec: int | str | dict) -> Any:
    """A QoS profile from a depth, a profile name or a mapping (already validated by config)."""
    from rclpy import qos

    if isinstance(spec, int):
        return qos.QoSProfile(depth=spec)
    if isinstance(spec, str):  # a name config.QOS_PROFILES admits
        return getattr(qos, f"qos_profile_{spec}")
    profile = qos.QoSProfile(depth=spec.get("depth", 10))
    for policy, values in (("reliability", qos.ReliabilityPolicy),
                           ("durability", qos.DurabilityPolicy), ("history", qos.HistoryPolicy)):
        if policy in spec:
            setattr(profile, policy, getattr(values, spec[policy].upper()))
    return profile


def is_reliable(spec: int | str | dict) -> bool:
    """Whether a topic's frames wait out a link loss: unless its QoS says best effort (the system
    default and best-available profiles are reliable with every shipped RMW). Without rclpy."""
    if isinstance(spec, str):
        return spec not in BEST_EFFORT_PROFILES
    return not (isinstance(spec, dict) and spec.get("reliability") == "best_effort")
