"""Placeholders: checking, the wildcard form, matching concrete keys, filling names."""

from __future__ import annotations

import pytest
from rosgate_transport_zenoh.placeholders import Template, check


def test_a_template_becomes_a_wildcard_matches_and_fills():
    keys, names = Template("fleet/{robot}/scan"), Template("/{robot}/scan")
    assert keys.wildcard() == "fleet/*/scan"
    assert names.wildcard() == "/*/scan"
    assert keys.match("fleet/robot07/scan") == {"robot": "robot07"}
    assert names.fill(keys.match("fleet/robot07/scan")) == "/robot07/scan"
    assert Template("/a/{robot}").fill({"robot": "r1"}) == "/a/r1"


@pytest.mark.parametrize("key", ["fleet/robot07/odom", "fleet/robot07/scan/x", "fleet/scan",
                                 "other/robot07/scan", "fleet/robot-7/scan", "fleet/7r/scan"])
def test_keys_that_do_not_fit_or_cannot_name_a_ros_topic_match_nothing(key):
    assert Template("fleet/{robot}/scan").match(key) is None


@pytest.mark.parametrize("text, words", [
    ("/{robt}/scan", "unknown placeholder {robt}"),
    ("/{robot}/{robot}", "only once"),
    ("/r_{robot}/scan", "a whole part between slashes"),
])
def test_wrong_placeholders_say_why(text, words):
    with pytest.raises(ValueError, match=words.replace("{", r"\{").replace("}", r"\}")):
        check(text)


def test_names_without_placeholders_have_none():
    assert check("/scan") == [] and check("fleet/a/b") == []
