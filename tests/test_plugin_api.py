"""The plugin API is what ``rosgate`` exports: each class and function of it says what it
promises, and docs/plugin-api.md names only what it exports, the bus facade included."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import rosgate

PAGE = Path(__file__).resolve().parents[1] / "docs" / "plugin-api.md"


def _table(heading: str) -> list[list[str]]:
    """The backticked words of the first cell of each row of the table under ``heading``."""
    text = PAGE.read_text()
    section = text[text.index(heading):]
    rows: list[list[str]] = []
    for line in section.splitlines()[1:]:
        if rows and not line.startswith("|"):
            break
        if line.startswith("| `"):
            rows.append(re.findall(r"`(\w+)", line.split("|")[1]))
    return rows


def test_every_public_class_and_function_has_a_docstring() -> None:
    public = {name: getattr(rosgate, name) for name in rosgate.__all__}
    missing = [name for name, found in public.items()
               if (inspect.isclass(found) or inspect.isfunction(found))
               and not (found.__doc__ or "").strip()]
    assert missing == []


def test_the_bus_names_the_page_lists_are_exported_and_the_facade_is_on_bus_role() -> None:
    heading = "## What a bus role, a bus and a service framing use"
    names = [name for row in _table(heading) for name in row]
    assert len(names) >= 30
    assert sorted(set(names) - set(rosgate.__all__)) == []
    members = [name for row in _table("| `BusRole` member |") for name in row]
    assert len(members) >= 12
    for member in members:
        found = getattr(rosgate.BusRole, member)
        assert (found.__doc__ or "").strip(), member
