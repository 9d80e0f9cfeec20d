"""Pattern entries: a ``topic:``, ``service:`` or ``action:`` written as a glob in the syntax of
the server's policy rules (``*`` and ``?`` within one name segment, ``**`` across segments) stands
for every name that appears and matches it. A pattern is a fixed head (``/robot1``) and a tail
with the wildcards (``/**``); its ``remote:`` keeps the tail and may change the head
(``/fleet/robot1/**``), so a matched name maps to its far-side name by its head alone."""

from __future__ import annotations

import re
from collections.abc import Iterable
from functools import lru_cache
from typing import Any

from .kinds import _NAME_TOKEN, ROS_NAME_MAX, Key, names, text

WILDCARDS = "*?"
#: a segment of a pattern: a name token with wildcards, or ``**`` alone
_SEGMENT = re.compile(r"\*\*|[A-Za-z0-9_*?]+")
#: names nobody wants bridged by accident: ROS's own log and parameter topics, the bridge's
#: diagnostics, every node's parameter and type-description services
DENY_DEFAULT = ("/rosout", "/parameter_events", "/diagnostics", "/**/describe_parameters",
                "/**/get_parameter_types", "/**/get_parameters", "/**/list_parameters",
                "/**/set_parameters", "/**/set_parameters_atomically",
                "/**/get_type_description")


def is_pattern(name: str) -> bool:
    return any(c in name for c in WILDCARDS)


@lru_cache(maxsize=1024)
def _glob(pattern: str) -> re.Pattern[str]:
    parts = re.split(r"(\*\*|\*|\?)", pattern)
    table = {"**": ".*", "*": "[^/]*", "?": "[^/]"}
    return re.compile("".join(table.get(p, re.escape(p)) for p in parts))


def matches(pattern: str, name: str) -> bool:
    """Whether ``name`` matches the glob ``pattern`` (a plain name matches itself only)."""
    return _glob(pattern).fullmatch(name) is not None


def denied(name: str, deny: Iterable[str]) -> str | None:
    """The first glob of ``deny`` that ``name`` matches (None: none does)."""
    return next((glob for glob in deny if matches(glob, name)), None)


def split(pattern: str) -> tuple[str, str]:
    """A pattern's head (the segments before the first wildcard) and its tail (from there)."""
    segments = pattern.split("/")[1:]
    first = next(i for i, s in enumerate(segments) if is_pattern(s))
    head = "".join(f"/{s}" for s in segments[:first])
    return head, pattern[len(head):]


def far_name(pattern: str, remote: str, name: str) -> str:
    """The far-side name of ``name`` (which matches ``pattern``): ``remote``'s head for
    ``pattern``'s."""
    return split(remote)[0] + name[len(split(pattern)[0]):]


def name_or_pattern(key: Key, value: Any) -> str:
    """a ROS name (`/robot1/scan`), or a pattern (`/robot1/**`: `*` and `?` within a segment,
    `**` across); `{placeholders}` in fleet entries"""
    from .kinds import ros_name

    name = text(key, value)
    if not is_pattern(name):
        return ros_name(key, name)
    example = f"{key.name}: /robot1/**"
    if not name.startswith("/"):
        raise key.error(f"a pattern starts with '/': '{name}'", fix=f"e.g. {example}")
    if len(name) > ROS_NAME_MAX:
        raise key.error(f"a pattern of {len(name)} characters is longer than a ROS name may be "
                        f"({ROS_NAME_MAX})", fix=f"e.g. {example}")
    for segment in name[1:].split("/"):
        if not _SEGMENT.fullmatch(segment) or "**" in segment and segment != "**":
            raise key.error(f"'{name}' is not a valid pattern: segment '{segment}'",
                            fix="use letters, digits, '_', '*' and '?' in parts separated by "
                                f"single '/', '**' only as a whole part, e.g. {example}")
    return name


def deny_list(key: Key, value: Any) -> tuple[str, ...]:
    """a list of names or patterns"""
    found = names(key, value)
    for glob in found:
        if not glob.startswith("/"):
            raise key.error(f"'{glob}' does not start with '/': it would match no name",
                            fix=f"write it as a full name or pattern, e.g. [/{glob}]")
        if not is_pattern(glob) and not all(_NAME_TOKEN.fullmatch(t) for t in glob[1:].split("/")):
            raise key.error(f"'{glob}' is not a valid ROS name",
                            fix="use letters, digits and '_' in parts separated by single '/'")
    return found
