"""rosgate.keys: the key_file / key_env convention every cipher shares. One OptionError naming
the option for every way the key can be missing or unreadable; the key never in a message.
Tables go through rosgate.options.parse, as the core reads a cipher's table, into KeyOptions."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from rosgate import OptionError
from rosgate.keys import KeyOptions, describe_source, key_source, load_key
from rosgate.options import parse

KEY = b"c2VjcmV0LWtleS1ieXRlcy1mb3ItdGVzdHMtb25seSE="


def write_key(path: Path, key: bytes = KEY, mode: int = 0o600) -> Path:
    path.write_bytes(b"  " + key + b"\n")
    path.chmod(mode)
    return path


class Demo:
    """A cipher's declaration, as far as keys go."""

    name = "demo"
    Options = KeyOptions


def key(table: dict, base_dir: Path) -> bytes:
    return load_key(parse(Demo, table), base_dir, "demo")


def option_error(table: dict, base_dir: Path) -> OptionError:
    with pytest.raises(OptionError) as info:
        key(table, base_dir)
    return info.value


def test_key_file_is_read_stripped_relative_to_the_base_dir_or_absolute(tmp_path):
    (tmp_path / "keys").mkdir()
    path = write_key(tmp_path / "keys" / "a.key")
    assert key({"key_file": "keys/a.key"}, tmp_path) == KEY
    assert key({"key_file": str(path)}, Path("/nonexistent")) == KEY


def test_key_env_is_read_stripped(tmp_path, monkeypatch):
    monkeypatch.setenv("ROSGATE_TEST_KEY", f"  {KEY.decode()}\n")
    assert key({"key_env": "ROSGATE_TEST_KEY"}, tmp_path) == KEY


@pytest.mark.parametrize("options", [{}, {"key_file": "a", "key_env": "B"}],
                         ids=["neither", "both"])
def test_exactly_one_source(tmp_path, options):
    error = option_error(options, tmp_path)
    assert error.key is None
    assert error.message == "demo needs exactly one of key_file or key_env"
    assert "rosgate keygen demo --out demo.key" in error.fix


def test_unknown_option_is_named(tmp_path):
    error = option_error({"key_file": "a", "keyfile": "a", "mode": 1}, tmp_path)
    assert (error.key, error.message) == ("keyfile",
                                          "unknown key 'keyfile' (did you mean 'key_file'?)")
    assert error.fix == "valid keys are key_file, key_env"


@pytest.mark.parametrize("table, name", [({"key_file": 5}, "key_file"),
                                         ({"key_env": ["K"]}, "key_env")])
def test_a_source_must_be_a_string(tmp_path, table, name):
    error = option_error(table, tmp_path)
    assert error.key == name
    assert error.message.startswith("expected a string or null, got ")


@pytest.mark.parametrize("make", [lambda d: None, lambda d: (d / "nope.key").mkdir()],
                         ids=["missing", "directory"])
def test_unreadable_key_file_names_the_path(tmp_path, make):
    make(tmp_path)
    error = option_error({"key_file": "nope.key"}, tmp_path)
    assert error.key == "key_file"
    assert str(tmp_path / "nope.key") in error.message
    assert "rosgate keygen demo" in error.fix


@pytest.mark.parametrize("value", [None, ""], ids=["unset", "empty"])
def test_key_env_unset_or_empty(tmp_path, monkeypatch, value):
    monkeypatch.delenv("ROSGATE_TEST_KEY", raising=False)
    if value is not None:
        monkeypatch.setenv("ROSGATE_TEST_KEY", value)
    error = option_error({"key_env": "ROSGATE_TEST_KEY"}, tmp_path)
    assert error.key == "key_env"
    assert error.message == "environment variable 'ROSGATE_TEST_KEY' is not set or empty"
    assert error.fix.startswith("export ROSGATE_TEST_KEY=")


@pytest.mark.parametrize("mode, warned", [(0o600, False), (0o400, False), (0o644, True),
                                          (0o640, True), (0o604, True), (0o660, True)])
def test_a_key_file_others_can_read_is_warned_about(tmp_path, caplog, mode, warned):
    path = write_key(tmp_path / "k.key", mode=mode)
    with caplog.at_level(logging.DEBUG, logger="rosgate"):
        assert key({"key_file": "k.key"}, tmp_path) == KEY
    messages = [r.getMessage() for r in caplog.records if r.name == "rosgate"]
    assert messages == ([f"key file {path} is readable by other users; chmod 600 it"]
                        if warned else [])
    assert all(KEY.decode() not in m for m in messages)


def test_where_a_key_came_from():
    in_file, in_env = KeyOptions(key_file="a.key"), KeyOptions(key_env="K")
    assert (key_source(in_file), describe_source(in_file)) == ("key_file", "file 'a.key'")
    assert (key_source(in_env), describe_source(in_env)) == ("key_env", "variable 'K'")
