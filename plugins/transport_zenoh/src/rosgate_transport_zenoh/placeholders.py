"""Placeholders: one fleet-wide entry for any number of robots.

A topic entry may name a robot by placeholder, in its ROS name and its key alike::

    - {topic: "/{robot}/scan", remote: "fleet/{robot}/scan", direction: receive, ...}

A placeholder is a whole chunk (between slashes) written ``{name}``; :data:`NAMES` are the ones
there are. On zenoh the key template becomes a subscription with ``*`` in its place, and each
concrete key that arrives (``fleet/robot7/scan``) gives the placeholder its value (``robot7``),
which fills the ROS name (``/robot7/scan``). No rclpy, no bus here: text only.
"""

from __future__ import annotations

import re

#: the placeholders there are: the robot (a fleet member's bridge name)
NAMES = ("robot",)

_FIELD = re.compile(r"\{([^{}/]*)\}")
# a value must be usable in a ROS name as a whole token
_VALUE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def names_in(text: str) -> list[str]:
    """The placeholder names in ``text``, in order (unknown ones too)."""
    return _FIELD.findall(text)


def has_placeholders(text: str) -> bool:
    return "{" in text or "}" in text


def check(text: str) -> list[str]:
    """The placeholders of ``text``; ``ValueError`` saying what is wrong with them."""
    found = names_in(text)
    for name in found:
        if name not in NAMES:
            raise ValueError(f"unknown placeholder {{{name}}} (there is: "
                             f"{', '.join('{' + n + '}' for n in NAMES)})")
    if len(set(found)) != len(found):
        raise ValueError("a placeholder may appear only once")
    for chunk in text.strip("/").split("/"):
        if has_placeholders(chunk) and not _FIELD.fullmatch(chunk):
            raise ValueError(f"a placeholder must be a whole part between slashes, not {chunk!r}")
    return found


class Template:
    """A name or key with placeholders: its wildcard form, matching and filling."""

    def __init__(self, text: str):
        check(text)
        self.text = text
        self.lead = "/" if text.startswith("/") else ""
        self.chunks = text.removeprefix("/").split("/")
        self.names = names_in(text)

    def wildcard(self) -> str:
        """A key expression matching every filling: each placeholder becomes ``*``."""
        return self.lead + "/".join("*" if _FIELD.fullmatch(c) else c for c in self.chunks)

    def match(self, concrete: str) -> dict[str, str] | None:
        """The values ``concrete`` gives the placeholders; None when it does not fit (or a
        value cannot stand in a ROS name)."""
        parts = concrete.removeprefix(self.lead).split("/")
        if len(parts) != len(self.chunks):
            return None
        values = {}
        for chunk, part in zip(self.chunks, parts, strict=True):
            field = _FIELD.fullmatch(chunk)
            if field is None:
                if chunk != part:
                    return None
            elif _VALUE.fullmatch(part):
                values[field.group(1)] = part
            else:
                return None
        return values

    def fill(self, values: dict[str, str]) -> str:
        return _FIELD.sub(lambda m: values[m.group(1)], self.text)

    def __repr__(self) -> str:
        return f"Template({self.text!r})"

