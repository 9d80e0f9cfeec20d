"""rosgate.options: a plugin's options declared once (a frozen dataclass of rosgate.option
fields) and every way a table can be wrong raised as an OptionError at its key, with a fix."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

import pytest

from rosgate import OptionError, option
from rosgate.options import as_options, declaration_problem, declared, parse, spell


class Demo:
    """A plugin class as far as options go."""

    name = "demo"

    @dataclass(frozen=True)
    class Options:
        host: str = option(doc="the far host")
        level: int = option(3, "how hard to try", minimum=1, maximum=9)
        ratio: float = option(0.5, "share of the link to use", minimum=0, maximum=1)
        fast: bool = option(False, "skip the checks")
        mode: Literal["push", "pull"] = option("push", "who starts")
        colour: str = option("red", "the colour of the log lines", choices=("red", "green"))
        names: list[str] = option([], "topics to leave out")
        extra: dict[str, Any] = option({}, "passed to the library as it is")
        timeout: float | None = option(None, "seconds to wait; null: forever", minimum=0)
        low: int = option(0, "first port")
        high: int = option(10, "last port")

        def __post_init__(self) -> None:
            if self.low > self.high:
                raise OptionError("high", f"must not be below low ({self.low})",
                                  "swap low and high")


def error(table: dict) -> OptionError:
    with pytest.raises(OptionError) as info:
        parse(Demo, table)
    return info.value


def test_a_table_becomes_the_options_instance_with_defaults_filled_in():
    options = parse(Demo, {"host": "a", "ratio": 1, "names": ["/x"], "extra": {"k": [1]}})
    assert options == Demo.Options(host="a", ratio=1.0, names=["/x"], extra={"k": [1]})
    assert type(options.ratio) is float  # an int is taken for a float, and becomes one
    assert (options.level, options.mode, options.timeout) == (3, "push", None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.level = 4  # type: ignore[misc]


def test_list_and_dict_defaults_are_not_shared():
    a, b = parse(Demo, {"host": "a"}), parse(Demo, {"host": "b"})
    a.names.append("/x")
    assert b.names == [] and a.extra is not b.extra


def test_an_unknown_key_suggests_the_closest_and_lists_them_all():
    e = error({"host": "a", "levle": 2})
    assert (e.key, e.message) == ("levle", "unknown key 'levle' (did you mean 'level'?)")
    assert e.fix == ("valid keys are host, level, ratio, fast, mode, colour, names, "
                     "extra, timeout, low, high")
    assert error({"host": "a", "zzz": 1}).message == "unknown key 'zzz'"


def test_a_class_with_empty_options_takes_none():
    class Bare:
        name = "bare"

        @dataclass(frozen=True)
        class Options:
            pass

    with pytest.raises(OptionError) as info:
        parse(Bare, {"fast": True})
    assert (info.value.key, info.value.message, info.value.fix) == (
        "fast", "unknown key 'fast'", "bare takes no options: remove it")


def test_a_missing_required_key_is_named_with_its_doc():
    e = error({})
    assert (e.key, e.message, e.fix) == ("host", "missing required key 'host' (the far host)",
                                         "add host: <a string> under plugins: demo:")


@pytest.mark.parametrize("key, value, message", [
    ("host", 5, "expected a string, got 5"),
    ("level", True, "expected an integer 1..9, got true (a boolean)"),  # never a number
    ("level", 2.0, "expected an integer 1..9, got 2.0"),
    ("level", "3", "expected an integer 1..9, got '3'"),
    ("ratio", False, "expected a number 0..1, got false (a boolean)"),
    ("ratio", "half", "expected a number 0..1, got 'half'"),
    ("fast", 1, "expected true or false, got 1"),
    ("fast", "yes", "expected true or false, got 'yes'"),
    ("mode", "both", "'both' is not one of push, pull"),
    ("mode", 1, "1 is not one of push, pull"),
    ("names", "/x", "expected a list (a string each), got '/x'"),
    ("names", ["/x", 2], "expected a list (a string each), got a list ['/x', 2]"),
    ("extra", ["k"], "expected a mapping, got a list ['k']"),
    ("extra", {1: "v"}, "expected a mapping, got a mapping"),     # keys are names
    ("timeout", "soon", "expected a number >= 0 or null, got 'soon'"),
    ("timeout", float("inf"), "expected a number >= 0 or null, got inf"),  # .inf is no number
    ("level", None, "expected an integer 1..9, got nothing"),
], ids=lambda v: str(v))
def test_a_value_of_the_wrong_type(key, value, message):
    e = error({"host": "a", key: value})
    assert (e.key, e.message) == (key, message)


def test_the_fix_says_what_the_option_is_and_takes():
    assert error({"host": "a", "level": "x"}).fix == (
        "level: how hard to try (an integer, 1..9, default 3)")
    assert error({"host": "a", "mode": 1}).fix == (
        "mode: who starts (one of: push, pull, default push)")
    assert error({"host": 1}).fix == "host: the far host (a string, required)"


@pytest.mark.parametrize("key, value, message", [
    ("level", 0, "expected an integer 1..9, got 0"),
    ("level", 10, "expected an integer 1..9, got 10"),
    ("ratio", 1.5, "expected a number 0..1, got 1.5"),
    ("timeout", -1, "expected a number >= 0 or null, got -1"),  # as written, not as converted
    ("colour", "blue", "'blue' is not one of red, green"),
    ("colour", "gren", "'gren' is not one of red, green (did you mean 'green'?)"),
])
def test_a_value_out_of_range_or_not_among_the_choices(key, value, message):
    e = error({"host": "a", key: value})
    assert (e.key, e.message) == (key, message)


def test_the_ends_of_a_range_are_in_it():
    assert parse(Demo, {"host": "a", "level": 9, "ratio": 0}).level == 9
    assert parse(Demo, {"host": "a", "timeout": 0}).timeout == 0.0


def test_rules_across_fields_live_in_post_init():
    e = error({"host": "a", "low": 5, "high": 4})
    assert (e.key, e.message, e.fix) == ("high", "must not be below low (5)", "swap low and high")


def test_a_class_without_options_takes_none_either():
    class Legacy:
        name = "legacy"

    with pytest.raises(OptionError) as info:
        parse(Legacy, {"anything": 1})
    assert (info.value.key, info.value.message, info.value.fix) == (
        "anything", "unknown key 'anything'", "legacy takes no options: remove it")
    assert parse(Legacy, {}) == {}


def test_as_options_keeps_what_the_core_parsed_and_parses_a_plain_mapping():
    parsed = parse(Demo, {"host": "a"})
    assert as_options(Demo, parsed) is parsed
    assert as_options(Demo, {"host": "a"}) == parsed
    with pytest.raises(OptionError):
        as_options(Demo, {})

    class Legacy:
        name = "legacy"

    assert as_options(Legacy, {}) == {}
    with pytest.raises(OptionError, match="unknown key 'x'") as info:
        as_options(Legacy, {"x": 1})
    assert info.value.fix == "legacy takes no options: remove it"


def test_declared_lists_each_option_for_the_listing():
    rows = {row.name: row for row in declared(Demo)}
    assert list(rows) == [f.name for f in dataclasses.fields(Demo.Options)]
    assert (rows["host"].required, rows["host"].default_text()) == (True, "required")
    assert (rows["timeout"].default_text(), rows["fast"].default_text()) == ("null", "false")
    assert (rows["names"].default_text(), rows["extra"].default_text()) == ("[]", "{}")
    assert rows["level"].limits() == "1..9"
    assert rows["timeout"].limits() == ">= 0"
    assert rows["mode"].limits() == rows["colour"].limits().replace("red, green", "push, pull")
    assert [spell(rows[n].type) for n in ("mode", "names", "extra", "timeout")] == [
        "str", "list[str]", "dict[str, Any]", "float | None"]
    assert declared(type("Legacy", (), {})) == []


def test_option_needs_a_doc():
    with pytest.raises(TypeError, match="option\\(\\) needs a doc"):
        option(1)


def test_a_malformed_declaration_is_named():
    def problem(body: type) -> str | None:
        return declaration_problem(type("Plugin", (), {"Options": body}))

    class Plain:
        level: int = 1

    assert problem(Plain) == ("Plugin.Options is not a frozen dataclass (decorate it with "
                              "@dataclass(frozen=True))")
    assert problem(dataclass(Plain)).startswith("Plugin.Options is not a frozen dataclass")

    @dataclass(frozen=True)
    class Unsupported:
        ports: set[int] = option(frozenset(), "ports")

    assert problem(Unsupported) == ("Plugin.Options.ports: the type set[int] is not an option "
                                    "type (str, int, float, bool, Literal[...], list[T], "
                                    "dict[str, T], T | None, Any)")

    @dataclass(frozen=True)
    class BadDefault:
        level: int = option(0, "how hard", minimum=1)

    assert problem(BadDefault) == ("Plugin.Options.level: its default does not fit: expected "
                                   "an integer >= 1, got 0")
    assert problem(Demo.Options) is None


class Paths:
    name = "paths"

    @dataclass(frozen=True)
    class Options:
        folder: str | None = option(None, "a folder, relative to the file", relative=True)
        label: str = option("x", "not a path")


def test_a_relative_option_is_read_from_the_files_folder(tmp_path):
    """A path option given as the file gives it is read from the bringup.yaml's folder, as a
    cipher's key_file is; an absolute one, a plain string and an absent one are left alone."""
    parsed = parse(Paths, {"folder": "certs", "label": "certs"}, tmp_path)
    assert parsed.folder == str(tmp_path / "certs") and parsed.label == "certs"
    assert parse(Paths, {"folder": "/etc/fleet"}, tmp_path).folder == "/etc/fleet"
    assert parse(Paths, {}, tmp_path).folder is None
    assert parse(Paths, {"folder": "certs"}).folder == "certs"  # no file: as given
    assert [row.relative for row in declared(Paths)] == [True, False]


def test_a_word_of_another_table_suggests_this_table_s_word():
    """A client's entry says topic:, a server's rule name:; either in the other's place is
    answered with the word this table uses, not just the list of keys."""
    from rosgate.options import did_you_mean, unknown

    assert unknown("topic", ["name", "direction", "types"])[0] == \
        "unknown key 'topic' (did you mean 'name'?)"
    assert did_you_mean("name", ["service", "type", "direction"])[0] == "service"
    assert did_you_mean("type", ["name", "types"])[0] == "types"
    assert did_you_mean("topicc", ["topic", "type"])[0] == "topic"  # spelling still helps
