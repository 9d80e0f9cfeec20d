"""The plugin manager: in-process plugins register classes by kind and name; every mistake a plugin
can make is recorded as a Failure naming it, and never stops the other plugins."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import types
from importlib import metadata
from pathlib import Path
from typing import Any

import pytest
from rosgate_message_tree import TreeCodec

import rosgate
from rosgate import (
    Cipher,
    Codec,
    DatagramTransport,
    LinkError,
    OptionError,
    StreamTransport,
    Transport,
    hookimpl,
    hookspecs,
)
from rosgate.builtin import CdrCodec, NoCipher
from rosgate.config import loads
from rosgate.engine import Engine
from rosgate.options import parse
from rosgate.plugins import DISABLE_VARIABLE, Failure, Plugins, Registration
from rosgate.roles import Bridge

ROOT = Path(__file__).resolve().parents[2]


class FakeCodec(Codec):
    """Implements what a codec must; the classes below add only a name."""

    def encode(self, message: Any) -> bytes:
        return b""

    def decode(self, data: bytes) -> Any:
        return None


class Alpha(DatagramTransport):
    name = "alpha"

    def bind(self, address):
        raise LinkError("alpha binds nothing")


class Beta(FakeCodec):
    name = "beta"


class Zeta(FakeCodec):
    name = "zeta"


class Gamma(Cipher):
    name = "gamma"

    def seal(self, header: bytes, payload: bytes) -> bytes:
        return payload

    def open(self, header: bytes, body: bytes) -> bytes:
        return body


class FakePlugin:
    """A plugin object: attributes as a module has them (hashable, as pluggy needs plugins)."""

    def __init__(self, **attributes: Any):
        self.__dict__.update(attributes)


def plugin(**hooks) -> FakePlugin:
    """A plugin object whose attributes are the given hook implementations."""
    return FakePlugin(**{name: hookimpl(function) for name, function in hooks.items()})


def registers(*classes):
    def hook(register):
        for cls in classes:
            register(cls)
    return hook


def boom(register):
    raise RuntimeError("boom")


# --- registration --------------------------------------------------------------------------------

def test_each_kind_is_registered_with_its_origin():
    plugins = Plugins()
    plugins.add(plugin(rosgate_transports=registers(Alpha), rosgate_codecs=registers(Beta, Zeta),
                       rosgate_ciphers=registers(Gamma)), "greek", "rosgate-greek", "1.0")
    assert plugins.failures == []
    assert plugins.names("transport") == ["alpha"]
    assert plugins.names("codec") == ["beta", "zeta"]
    assert plugins.names("cipher") == ["gamma"]
    assert plugins.get("codec", "zeta") == Registration("codec", "zeta", Zeta, "greek",
                                                        "rosgate-greek", "1.0")
    assert plugins.get("transport", "alpha").cls is Alpha
    assert plugins.get("cipher", "gamma").cls is Gamma
    assert plugins.get("codec", "alpha") is None  # names are per kind


def test_a_class_instance_with_decorated_methods():
    class Provider:
        @hookimpl
        def rosgate_codecs(self, register):
            register(Beta)

        @hookimpl
        def rosgate_ciphers(self, register):
            register(Gamma)

    plugins = Plugins()
    plugins.add(Provider(), "provider", "rosgate-provider", "2.0")
    assert plugins.failures == []
    assert plugins.names("codec") == ["beta"] and plugins.names("cipher") == ["gamma"]
    assert plugins.get("codec", "beta").plugin == "provider"


def test_the_builtin_module_registers_cdr_and_none():
    plugins = Plugins()
    plugins.add(rosgate.builtin, "builtin", "rosgate", rosgate.__version__)
    assert plugins.get("codec", "cdr").cls is CdrCodec
    assert plugins.get("cipher", "none").cls is NoCipher
    assert plugins.names("transport") == []


def test_an_implementation_without_the_register_argument_is_allowed():
    calls: list[str] = []
    plugins = Plugins()
    plugins.add(plugin(rosgate_transports=lambda: calls.append("transports"),
                       rosgate_codecs=registers(Beta)), "lazy", "rosgate-lazy")
    assert plugins.failures == []
    assert calls == ["transports"]  # called once, with nothing
    assert plugins.names("codec") == ["beta"]


def test_a_hook_only_runs_for_the_plugin_being_added():
    calls: list[str] = []
    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=lambda register: calls.append("first")), "first")
    plugins.add(plugin(rosgate_codecs=lambda register: calls.append("second")), "second")
    assert calls == ["first", "second"]


def test_a_hook_that_raises_is_a_failure_naming_the_plugin_and_the_others_still_register():
    plugins = Plugins()
    plugins.add(plugin(rosgate_ciphers=registers(Gamma)), "before", "rosgate-before")
    plugins.add(plugin(rosgate_codecs=boom, rosgate_transports=registers(Alpha)), "broken",
                "rosgate-broken", "0.1")
    plugins.add(plugin(rosgate_codecs=registers(Beta)), "after", "rosgate-after")
    assert len(plugins.failures) == 1
    failure = plugins.failures[0]
    assert (failure.plugin, failure.distribution) == ("broken", "rosgate-broken")
    assert failure.reason.startswith("rosgate_codecs: RuntimeError: boom (")
    assert "test_plugins.py" in failure.reason  # where it raised
    # the broken plugin's other hook and the other plugins worked
    assert plugins.names("transport") == ["alpha"]
    assert plugins.names("codec") == ["beta"]
    assert plugins.names("cipher") == ["gamma"]


def test_classes_registered_before_a_hook_raised_are_not_kept():
    def half(register):
        register(Beta)
        raise ValueError("half way")

    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=half), "half", "rosgate-half")
    assert plugins.names("codec") == []
    assert [f.reason.split(" (")[0] for f in plugins.failures] == [
        "rosgate_codecs: ValueError: half way"]


class NotAPlugin:
    name = "plain"


class NoName(FakeCodec):
    pass


class BadName(FakeCodec):
    name = "two words"


class EmptyName(FakeCodec):
    name = ""


class NumberName(FakeCodec):
    name = 3


@pytest.mark.parametrize("hook, registered, problem", [
    ("rosgate_codecs", NotAPlugin, "which is not a subclass of rosgate.Codec"),
    ("rosgate_codecs", Alpha, "which is not a subclass of rosgate.Codec"),       # wrong kind
    ("rosgate_transports", Beta, "which is not a subclass of rosgate.Transport"),
    ("rosgate_ciphers", Gamma({}, "."), "which is not a subclass of rosgate.Cipher"),  # an instance
    ("rosgate_ciphers", "fernet", "which is not a subclass of rosgate.Cipher"),
    ("rosgate_codecs", NoName, "NoName has no valid 'name'"),
    ("rosgate_codecs", BadName, "BadName has no valid 'name'"),
    ("rosgate_codecs", EmptyName, "EmptyName has no valid 'name'"),
    ("rosgate_codecs", NumberName, "NumberName has no valid 'name'"),
], ids=["plain-class", "transport-as-codec", "codec-as-transport", "instance", "string", "no-name",
        "two-words", "empty", "number"])
def test_an_invalid_class_is_a_failure_and_valid_ones_beside_it_register(hook, registered, problem):
    valid = {"rosgate_codecs": Zeta, "rosgate_transports": Alpha, "rosgate_ciphers": Gamma}[hook]
    plugins = Plugins()
    plugins.add(plugin(**{hook: registers(registered, valid)}), "sloppy", "rosgate-sloppy")
    assert len(plugins.failures) == 1
    failure = plugins.failures[0]
    assert (failure.plugin, failure.distribution) == ("sloppy", "rosgate-sloppy")
    assert problem in failure.reason
    assert [r.cls for r in plugins.registered.values()] == [valid]


def test_an_unknown_hook_argument_is_a_failure_at_registration():
    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=lambda register, colour: None), "odd", "rosgate-odd")
    plugins.add(plugin(rosgate_codecs=registers(Beta)), "fine", "rosgate-fine")
    assert [(f.plugin, f.distribution) for f in plugins.failures] == [("odd", "rosgate-odd")]
    assert "colour" in plugins.failures[0].reason
    assert plugins.names("codec") == ["beta"]


def test_the_same_name_twice_the_first_wins():
    class OtherBeta(FakeCodec):
        name = "beta"

    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=registers(Beta)), "one", "rosgate-codec-one", "1.0")
    plugins.add(plugin(rosgate_codecs=registers(OtherBeta, Zeta)), "two", "rosgate-codec-two",
                "2.0")
    assert plugins.get("codec", "beta").cls is Beta
    assert plugins.get("codec", "zeta").plugin == "two"
    assert plugins.failures == [Failure("two", "rosgate-codec-two",
                                        "codec 'beta' is already provided by rosgate-codec-one; "
                                        "skipped")]


def test_the_same_name_in_different_kinds_is_not_a_clash():
    class BetaTransport(StreamTransport):
        name = "beta"

        def listen(self, address):
            raise LinkError("no")

        def connect(self, address, timeout):
            raise OSError("no")

    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=registers(Beta),
                       rosgate_transports=registers(BetaTransport)), "b")
    assert plugins.failures == []
    assert plugins.get("codec", "beta").cls is Beta
    assert plugins.get("transport", "beta").cls is BetaTransport


def test_a_plugin_name_added_twice_is_a_failure():
    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=registers(Beta)), "dup", "rosgate-first")
    plugins.add(plugin(rosgate_codecs=registers(Zeta)), "dup", "rosgate-second")
    assert plugins.names("codec") == ["beta"]
    assert plugins.failures == [Failure("dup", "rosgate-second",
                                        "a plugin of this name is already loaded")]


def test_remove_forgets_a_plugins_registrations():
    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=registers(Beta), rosgate_ciphers=registers(Gamma)), "gone")
    plugins.add(plugin(rosgate_codecs=registers(Zeta)), "stays")
    plugins.remove("gone")
    assert plugins.names("codec") == ["zeta"]
    assert plugins.names("cipher") == []
    assert plugins.get("codec", "beta") is None
    # the name and the class names are free again
    plugins.add(plugin(rosgate_codecs=registers(Beta)), "gone", "rosgate-again")
    assert plugins.get("codec", "beta").distribution == "rosgate-again"
    assert plugins.failures == []


# --- pluggy finds the hooks: every rosgate_* function is one, a misspelt one is a failure --------

def module(name: str, source: str, **names: Any) -> types.ModuleType:
    """A plugin module made from source, as an entry point imports it; ``names`` are in scope."""
    made = types.ModuleType(name)
    made.__dict__.update(names)
    exec(textwrap.dedent(source), made.__dict__)
    return made


HOOKS = ("the hooks are rosgate_bus_roles, rosgate_ciphers, rosgate_codecs, rosgate_commands, "
         "rosgate_monitors, rosgate_packetizers, rosgate_service_framings, rosgate_transforms, "
         "rosgate_transports")


def test_a_misspelt_hook_is_a_failure_naming_it_and_nothing_of_the_plugin_is_kept():
    typo = module("rosgate_typo", """
        from rosgate import hookimpl

        @hookimpl
        def rosgate_transport(register):
            register(Alpha)

        @hookimpl
        def rosgate_codecs(register):
            register(Beta)
    """, Alpha=Alpha, Beta=Beta)
    plugins = Plugins()
    plugins.add(typo, "typo", "rosgate-typo", "1.0")
    plugins.add(plugin(rosgate_ciphers=registers(Gamma)), "fine")
    assert plugins.failures == [Failure(
        "typo", "rosgate-typo",
        f"unknown hook 'rosgate_transport' (did you mean 'rosgate_transports'?); {HOOKS}")]
    assert plugins.names("transport") == [] and plugins.names("codec") == []
    assert plugins.names("cipher") == ["gamma"]  # the next plugin is not taken down
    assert not plugins.manager.has_plugin("typo")


def test_an_unmarked_misspelt_hook_is_caught_too():
    plugins = Plugins()
    plugins.add(module("rosgate_typos", """
        def rosgate_cipher(register):
            pass

        def rosgate_kodecs(register):
            pass
    """), "typos")
    assert [f.reason for f in plugins.failures] == [
        "unknown hook 'rosgate_cipher' (did you mean 'rosgate_ciphers'?), 'rosgate_kodecs' "
        f"(did you mean 'rosgate_codecs'?); {HOOKS}"]


def test_every_rosgate_function_is_a_hook_marked_or_not_and_nothing_else_is():
    plain = module("rosgate_plain", """
        rosgate_version = "1.0"           # not a function: not a hook

        def helper(register):             # not named rosgate_*: not a hook
            raise AssertionError("called")

        def rosgate_codecs(register):     # a hook without the marker, as pytest_* are
            register(Beta)
    """, Beta=Beta)
    plugins = Plugins()
    plugins.add(plain, "plain")
    assert plugins.failures == []
    assert plugins.names("codec") == ["beta"]


class JsonCodec(Codec):  # forgot decode
    name = "json"

    def encode(self, message: Any) -> bytes:
        return b"{}"


class Silent(Cipher):
    name = "silent"


class Deaf(DatagramTransport):
    name = "deaf"


class HalfStream(StreamTransport):
    name = "half"

    def listen(self, address):
        raise LinkError("no")


class Unparsed(TreeCodec):
    name = "unparsed"


@pytest.mark.parametrize("hook, cls, reason", [
    ("rosgate_codecs", JsonCodec, "JsonCodec does not implement decode"),
    ("rosgate_ciphers", Silent, "Silent does not implement open, seal"),
    ("rosgate_transports", Deaf, "Deaf does not implement bind"),
    ("rosgate_transports", HalfStream, "HalfStream does not implement connect"),
    ("rosgate_codecs", Unparsed, "Unparsed does not implement parse"),
], ids=["codec", "cipher", "datagram", "stream", "tree-codec"])
def test_an_abstract_class_is_refused_naming_what_it_does_not_implement(hook, cls, reason):
    plugins = Plugins()
    plugins.add(plugin(**{hook: registers(cls)}), "abstract", "rosgate-abstract")
    assert plugins.failures == [Failure("abstract", "rosgate-abstract", reason)]
    assert plugins.registered == {}


def test_a_transport_of_no_kind_is_refused():
    class Undecided(Transport):
        name = "undecided"

    plugins = Plugins()
    plugins.add(plugin(rosgate_transports=registers(Undecided)), "undecided")
    assert [f.reason for f in plugins.failures] == [
        "Undecided is no kind of link (subclass DatagramTransport, StreamTransport or "
        "BusTransport, since rosgate plugin API 2: docs/plugin-api.md)"]


def test_options_that_are_not_a_frozen_dataclass_are_refused():
    class Sloppy(FakeCodec):
        name = "sloppy"

        class Options:
            level = 1

    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=registers(Sloppy)), "sloppy")
    assert [f.reason for f in plugins.failures] == [
        "Sloppy.Options is not a frozen dataclass (decorate it with @dataclass(frozen=True))"]


def test_a_transport_that_says_its_kind_by_an_attribute_is_refused():
    """The kind is the base class, and nothing else: ``stream = False`` on a plain Transport
    makes no datagram link."""
    class Old(Transport):
        name = "old"
        stream = False

        def bind(self, address):
            raise LinkError("not in this test")

    plugins = Plugins()
    plugins.add(plugin(rosgate_transports=registers(Old)), "old", "rosgate-transport-old")
    assert plugins.get("transport", "old") is None
    assert plugins.failures == [Failure("old", "rosgate-transport-old", "Old is no kind of link "
                                        "(subclass DatagramTransport, StreamTransport or "
                                        "BusTransport, since rosgate plugin API 2: "
                                        "docs/plugin-api.md)")]


def test_a_transport_without_options_registers_and_takes_none():
    class Plain(DatagramTransport):
        name = "plain"

        def __init__(self, options):
            super().__init__(options)
            self.max_frame = options.get("max_frame", 100)

        def bind(self, address):
            raise LinkError("not in this test")

    plugins = Plugins()
    plugins.add(plugin(rosgate_transports=registers(Plain)), "plain", "rosgate-transport-plain")
    assert plugins.failures == [] and plugins.get("transport", "plain").cls is Plain
    with pytest.raises(OptionError, match="unknown key 'max_frame'") as info:
        parse(Plain, {"max_frame": 64})
    assert info.value.fix == "plain takes no options: remove it"
    plain = Plain(parse(Plain, {}))
    assert (plain.options, plain.max_frame) == ({}, 100)


# --- lazy discovery ------------------------------------------------------------------------------

def test_asking_for_a_name_loads_its_entry_point_first_and_the_others_only_if_needed(monkeypatch):
    loaded: list[str] = []

    def entry_point(name: str, hook: str, cls: type) -> metadata.EntryPoint:
        def register_it(register):
            loaded.append(name)
            register(cls)
        made = module(f"rosgate_fake_{name}", "", **{hook: register_it})
        monkeypatch.setitem(sys.modules, made.__name__, made)
        return metadata.EntryPoint(name, made.__name__, "rosgate")

    found = [entry_point("beta", "rosgate_codecs", Beta),
             entry_point("greek", "rosgate_ciphers", Gamma),
             entry_point("zeta", "rosgate_codecs", Zeta),
             metadata.EntryPoint("builtin", "rosgate.builtin", "rosgate")]
    monkeypatch.setattr(metadata, "entry_points", lambda group: found)
    plugins = Plugins.discover()
    assert loaded == []  # listing imports nothing; builtin is the core's own
    assert plugins.get("codec", "cdr").cls is CdrCodec and loaded == []
    assert plugins.get("codec", "beta").cls is Beta and loaded == ["beta"]
    # no entry point named gamma: the others are loaded, each once
    assert plugins.get("cipher", "gamma").cls is Gamma and loaded == ["beta", "greek", "zeta"]
    assert plugins.get("codec", "nope") is None and loaded == ["beta", "greek", "zeta"]
    assert plugins.names("codec") == ["beta", "cdr", "zeta"]


def test_asking_for_udp_imports_no_other_plugin():
    """In a fresh process: the real entry points, the real modules."""
    code = ("import sys; from rosgate.plugins import Plugins; plugins = Plugins.discover(); "
            "before = sorted(m for m in sys.modules if m.startswith('rosgate_')); "
            "assert plugins.get('transport', 'udp') is not None; "
            "print(before, sorted(m for m in sys.modules if m.startswith('rosgate_')))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.split() == ["[]", "['rosgate_transport_udp']"], result.stdout


#: libraries that take tens to hundreds of milliseconds to import, which a plugin imports where it
#: uses them (a codec's converters, a cipher's box, a monitor's start, a command's run)
SLOW_TO_IMPORT = ("numpy", "rich", "prometheus_client", "nacl")


def test_loading_a_plugin_imports_no_library_that_is_slow_to_import():
    """In a fresh process: every installed entry point loaded, one at a time, as ``rosgate
    --help`` and ``rosgate check`` load them all; none may bring one of those libraries."""
    code = textwrap.dedent(f"""
        import sys
        from importlib import metadata
        from rosgate.plugins import ENTRY_POINT_GROUP, Plugins

        plugins = Plugins()
        for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            plugins.add(ep.load(), ep.name)
            print(ep.name, *[m for m in {SLOW_TO_IMPORT!r} if m in sys.modules])
        print("failures", len(plugins.failures))
    """)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, check=True)
    lines = result.stdout.splitlines()
    assert lines[-1] == "failures 0", result.stdout
    loaded = [line.split() for line in lines[:-1]]
    assert {"msgpack", "cbor", "nacl", "metrics", "top"} <= {name for name, *_ in loaded}
    assert [line for line in loaded if len(line) > 1] == [], result.stdout


# --- the hooks are documented where plugin authors read -------------------------------------------

def test_every_hook_is_documented_in_its_spec_and_in_the_guide():
    guide = (ROOT / "docs" / "plugins.md").read_text()
    hooks = [name for name in dir(hookspecs) if name.startswith("rosgate_")]
    assert hooks == ["rosgate_bus_roles", "rosgate_ciphers", "rosgate_codecs", "rosgate_commands",
                     "rosgate_monitors", "rosgate_packetizers", "rosgate_service_framings",
                     "rosgate_transforms", "rosgate_transports"]
    for name in hooks:
        assert getattr(hookspecs, name).__doc__, f"{name} has no docstring"
        assert name in guide, f"docs/plugins.md does not mention {name}"


# --- transforms and packetizers: also known by what they put on the wire --------------------------

class Squash(rosgate.Transform):
    name = "squash"
    wire_id = 200

    def encode(self, payload: bytes) -> bytes | None:
        return None

    def decode(self, data: bytes) -> bytes:
        return data


class Twice(rosgate.Packetizer):
    name = "twice"
    magic = (b"X2",)

    def cut(self, frame, sender, to, options):
        return [frame]

    def feed(self, packet, source, now):
        return None

    @classmethod
    def cost(cls, frame, max_frame, options):
        return frame, 1


def test_transforms_and_packetizers_are_found_by_name_and_by_what_they_put_on_the_wire():
    plugins = Plugins()
    plugins.add(plugin(rosgate_transforms=registers(Squash),
                       rosgate_packetizers=registers(Twice)), "mine")
    assert plugins.failures == []
    assert plugins.get("transform", "squash").cls is Squash
    assert plugins.by_wire("transform", 200).cls is Squash
    assert plugins.by_wire("packetizer", b"X2").cls is Twice
    assert plugins.by_wire("packetizer", b"X3") is None
    plugins.remove("mine")
    assert plugins.by_wire("transform", 200) is None


def test_a_second_plugin_with_the_same_wire_id_or_magic_is_a_failure():
    other_squash = type("OtherSquash", (Squash,), {"name": "other"})
    other_twice = type("OtherTwice", (Twice,), {"name": "thrice", "magic": (b"X3", b"X2")})
    plugins = Plugins()
    plugins.add(plugin(rosgate_transforms=registers(Squash),
                       rosgate_packetizers=registers(Twice)), "first", "rosgate-first")
    plugins.add(plugin(rosgate_transforms=registers(other_squash),
                       rosgate_packetizers=registers(other_twice)), "second", "rosgate-second")
    assert [f.reason for f in plugins.failures] == [
        "transform 'other' has the wire_id of 'squash' (rosgate-first); skipped",
        "packetizer 'thrice' has the magic of 'twice' (rosgate-first); skipped"]
    assert plugins.get("packetizer", "thrice") is None
    assert plugins.by_wire("packetizer", b"X3") is None  # nothing of the refused class is kept


@pytest.mark.parametrize("attributes, reason", [
    ({"wire_id": 0}, "BadSquash has no valid 'wire_id' (1..255, the byte that names it)"),
    ({"wire_id": True}, "BadSquash has no valid 'wire_id' (1..255, the byte that names it)"),
    ({"wire_id": 256}, "BadSquash has no valid 'wire_id' (1..255, the byte that names it)"),
])
def test_a_transform_needs_a_byte_that_names_it(attributes, reason):
    plugins = Plugins()
    plugins.add(plugin(rosgate_transforms=registers(type("BadSquash", (Squash,), attributes))),
                "bad")
    assert [f.reason for f in plugins.failures] == [reason]


@pytest.mark.parametrize("magic, reason", [
    (b"X2", "BadTwice has no valid 'magic' (a tuple of two-byte bytes: (b'XY',))"),
    ((b"XYZ",), "BadTwice has no valid 'magic' (a tuple of two-byte bytes: (b'XY',))"),
    ((), "BadTwice has no valid 'magic' (a tuple of two-byte bytes: (b'XY',))"),
    ((b"RG",), "BadTwice claims a magic of the link's own (b'RG', b'RB')"),
    ((b"X9", b"RB"), "BadTwice claims a magic of the link's own (b'RG', b'RB')"),
])
def test_a_packetizer_needs_magic_of_its_own(magic, reason):
    plugins = Plugins()
    plugins.add(plugin(rosgate_packetizers=registers(type("BadTwice", (Twice,),
                                                          {"magic": magic}))), "bad")
    assert [f.reason for f in plugins.failures] == [reason]


# --- explaining a missing plugin -----------------------------------------------------------------

def test_explain_missing_lists_installed_names_and_the_distribution_to_install():
    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=registers(Zeta, Beta)), "greek")
    message, fix = plugins.explain_missing("codec", "cbor")
    assert message == "unknown codec 'cbor' (installed codecs: beta, zeta)"
    assert fix == ("pip install the distribution that provides it (by convention "
                   "rosgate-codec-cbor), or pick an installed codec")


@pytest.mark.parametrize("kind, name, distribution", [
    ("cipher", "nacl", "rosgate-crypto-nacl"),
    ("cipher", "aesgcm", "rosgate-crypto-aesgcm"),   # the crypto- prefix for ciphers
    ("transport", "lora", "rosgate-transport-lora"),
    ("transport", "bt", "rosgate-transport-bt"),
    ("codec", "protobuf", "rosgate-codec-protobuf"),
])
def test_explain_missing_names_the_distribution(kind, name, distribution):
    message, fix = Plugins().explain_missing(kind, name)
    assert message == f"unknown {kind} {name!r} (installed {kind}s: none)"
    assert fix == (f"pip install the distribution that provides it (by convention {distribution}), "
                   f"or pick an installed {kind}")


@pytest.mark.parametrize("kind, name, distribution", [
    ("packetizer", "fec", "rosgate-recovery"),
    ("packetizer", "retransmit", "rosgate-recovery"),
    ("service_framing", "serial_datagram", "rosgate-mcu-cvra"),
    ("bus_role", "fleet", "rosgate-fleet"),
    ("packetizer", "compact", "rosgate-compact"),
])
def test_explain_missing_names_rosgate_s_own_distribution_where_the_convention_does_not(
        kind, name, distribution):
    message, fix = Plugins().explain_missing(kind, name)
    what = kind.replace("_", " ")
    assert message == f"unknown {what} {name!r} (installed {what}s: none)"
    pick = "" if kind == "bus_role" else f", or pick an installed {what}"  # the bus names it
    assert fix == f"pip install the distribution that provides it ({distribution}){pick}"


def test_explain_missing_gives_the_reason_a_plugin_failed():
    plugins = Plugins()
    plugins.add(plugin(rosgate_codecs=boom), "cbor", "rosgate-codec-cbor")
    message, fix = plugins.explain_missing("codec", "cbor")
    assert message.startswith("unknown codec 'cbor' (installed codecs: none); plugin 'cbor' is "
                              "installed but failed to load: rosgate_codecs: RuntimeError: boom")
    assert "blocked" not in message
    assert fix == "repair or reinstall rosgate-codec-cbor, or pick an installed codec"


def test_explain_missing_says_when_a_plugin_is_blocked():
    plugins = Plugins(blocked=["nacl"])
    message, fix = plugins.explain_missing("cipher", "nacl")
    assert message == ("unknown cipher 'nacl' (installed ciphers: none); "
                       f"plugin 'nacl' is blocked by {DISABLE_VARIABLE}")
    assert DISABLE_VARIABLE == "ROSGATE_DISABLE_PLUGINS"
    assert fix == "remove nacl from ROSGATE_DISABLE_PLUGINS, or pick an installed cipher"


# --- discovery through entry points --------------------------------------------------------------

def test_discover_finds_the_installed_plugins(monkeypatch):
    monkeypatch.delenv(DISABLE_VARIABLE, raising=False)
    plugins = Plugins.discover()
    assert plugins.failures == [] and plugins.blocked == []
    assert {"cdr", "msgpack"} <= set(plugins.names("codec"))
    assert {"none", "fernet"} <= set(plugins.names("cipher"))
    assert {"udp", "tcp"} <= set(plugins.names("transport"))
    cdr = plugins.get("codec", "cdr")
    assert (cdr.plugin, cdr.distribution, cdr.cls) == ("builtin", "rosgate", CdrCodec)
    assert plugins.get("cipher", "fernet").distribution == "rosgate-crypto-fernet"


def test_discover_honours_the_disable_variable(monkeypatch):
    monkeypatch.setenv(DISABLE_VARIABLE, "msgpack,fernet,cbor,nacl,json,aead")
    plugins = Plugins.discover()
    assert sorted(plugins.blocked) == ["aead", "cbor", "fernet", "json", "msgpack", "nacl"]
    assert plugins.names("codec") == ["cdr"]
    assert plugins.names("cipher") == ["none"]
    assert {"udp", "tcp"} <= set(plugins.names("transport"))
    message, fix = plugins.explain_missing("cipher", "fernet")
    assert "blocked by ROSGATE_DISABLE_PLUGINS" in message
    assert fix.startswith("remove fernet from ROSGATE_DISABLE_PLUGINS")


def test_builtin_cannot_be_blocked(monkeypatch):
    monkeypatch.setenv(DISABLE_VARIABLE, " builtin , msgpack ,, ")
    plugins = Plugins.discover()
    assert plugins.blocked == ["msgpack"]
    assert plugins.names("codec") == ["cbor", "cdr", "json"]
    assert plugins.names("cipher") == ["aead", "fernet", "nacl", "none"]
    assert plugins.get("cipher", "none").cls is NoCipher


# --- a transport's LinkError reaches the user at the key that opened the link ---------------------

@pytest.mark.parametrize("error, fix", [
    (LinkError("cannot bind UDP 0.0.0.0:5: Address already in use"),
     "free the port, or pick another one"),
    (LinkError("python-can cannot open socketcan channel can0: Network is down",
               fix="bring the interface up: ip link set can0 up type can bitrate 500000"),
     "bring the interface up: ip link set can0 up type can bitrate 500000"),
], ids=["core-default", "transport-fix"])
def test_a_link_error_is_located_with_the_transports_fix_or_the_default(error, fix):
    config = loads("bridge: {name: a, role: peer, peer: h, insecure: true}\n"
                   "topics:\n  - {topic: /t, type: std_msgs/msg/String, direction: receive, "
                   "port: 5}\n",
                   file="x.yaml")
    engine = Engine(config).prepare()
    bridge = Bridge(config, engine.plan, engine.resolver, None, engine.life)  # type: ignore[arg-type]
    located = bridge.link_error(error, "topics[0].port")
    assert str(located) == f"x.yaml:3: topics[0].port: {error}\n  fix: {fix}"
