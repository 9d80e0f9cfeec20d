"""docs/configuration.md's reference is generated from the schema: it lists every key the loader
takes, and a change to the schema that is not regenerated fails here, naming the command."""

from __future__ import annotations

from pathlib import Path

import pytest
from rosgate_docgen import BEGIN, COMMAND, END, render

from rosgate.config import BridgeConfig, ServiceConfig, TopicConfig, loads
from rosgate.config.kinds import keys
from rosgate.errors import ConfigError

PAGE = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def test_the_reference_is_up_to_date():
    page = PAGE.read_text(encoding="utf-8")
    assert render(page) == page, f"docs/configuration.md is stale: run {COMMAND}"


def test_the_walk_through_stays_above_the_generated_part():
    page = PAGE.read_text(encoding="utf-8")
    head = page.partition(BEGIN.format(command=COMMAND))[0]
    assert "## A client file, walked through" in head and "## Peer role" in head
    assert page.rstrip().endswith(END)
    assert render("intro\n" + BEGIN.format(command=COMMAND) + "\nold\n" + END + "\n").startswith(
        "intro\n")


def test_every_key_the_loader_takes_has_a_row():
    page = PAGE.read_text(encoding="utf-8")
    for section, prefix in ((TopicConfig, ""), (ServiceConfig, ""), (BridgeConfig, "bridge.")):
        for row in keys(section):
            if row.parse is None or not hasattr(row.parse, "section"):
                assert f"| `{prefix}{row.key}` | {row.doc} |" in page, row.key
    assert "| `bridge.limits.sessions` |" in page
    assert "| `bridge.links.<transport>.bandwidth` |" in page


def test_the_example_error_is_what_the_loader_says():
    page = PAGE.read_text(encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        loads("bridge: {name: a, role: client, server: 'h:1'}\ntopics:\n"
              "  - {topic: /a, type: std_msgs/msg/String, direction: transmit, codek: cdr}\n",
              file="bringup.yaml")
    assert f"  fix: {info.value.fix}\n" in page


def test_render_refuses_a_page_without_markers():
    with pytest.raises(ValueError, match="no markers"):
        render("# a page\n")
