"""``rosgate plugins``, ``rosgate check`` and the verbs plugins add, as plugin authors and users
meet them, with real installed-style plugins (a distribution's metadata, its entry point and its
module on PYTHONPATH): a misspelt hook reported by name, every mistake in a plugin's options
located at file:line:key with the fix, a plugin's options listed, columns aligned; a third
party's ``rosgate <verb>`` run with its arguments, and a plugin whose verb fails costing only
that verb."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROSGATE = str(Path(sys.executable).with_name("rosgate"))
HOOKS = ("the hooks are rosgate_bus_roles, rosgate_ciphers, rosgate_codecs, rosgate_commands, "
         "rosgate_monitors, rosgate_packetizers, rosgate_service_framings, rosgate_transforms, "
         "rosgate_transports")

TYPO = """
    from rosgate import hookimpl
    from rosgate_transport_udp import UdpTransport

    @hookimpl
    def rosgate_transport(register):  # the hook is rosgate_transports
        register(UdpTransport)
"""

KNOBS = """
    from dataclasses import dataclass
    from typing import Literal

    from rosgate import Codec, OptionError, option


    class KnobsCodec(Codec):
        name = "knobs"
        raw = True

        @dataclass(frozen=True)
        class Options:
            host: str = option(doc="where the knobs are")
            level: int = option(3, "how hard to try", minimum=1, maximum=9)
            mode: Literal["push", "pull"] = option("push", "who starts")
            colour: str = option("red", "colour of the log lines", choices=["red", "green"])
            names: list[str] = option([], "names to leave out")
            low: int = option(0, "first port")
            high: int = option(10, "last port")

            def __post_init__(self):
                if self.low > self.high:
                    raise OptionError("high", f"must not be below low ({self.low})",
                                      "swap low and high")

        def encode(self, message):
            return message

        def decode(self, data):
            return data


    def rosgate_codecs(register):
        register(KnobsCodec)
"""

LONG = """
    from rosgate import DatagramTransport


    class LongTransport(DatagramTransport):
        name = "long"

        def bind(self, address):
            raise OSError("not in this test")


    def rosgate_transports(register):
        register(LongTransport)
"""

KINDLESS = """
    from rosgate import Transport


    class OldTransport(Transport):  # says its kind with an attribute, not with its base
        name = "old"
        stream = False

        def bind(self, address):
            raise OSError("not in this test")


    def rosgate_transports(register):
        register(OldTransport)
"""


def install(site: Path, distribution: str, entry_point: str, source: str) -> None:
    """A one-module distribution laid out in ``site`` as pip lays it out."""
    module = distribution.replace("-", "_")
    info = site / f"{module}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {distribution}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[rosgate]\n{entry_point} = {module}\n")
    (site / f"{module}.py").write_text(textwrap.dedent(source))


@pytest.fixture
def site(tmp_path: Path) -> Path:
    site = tmp_path / "site"
    site.mkdir()
    return site


def rosgate(site: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([ROSGATE, *args], capture_output=True, text=True, timeout=60,
                          env=dict(os.environ, PYTHONPATH=str(site), **env))


BRINGUP = """\
bridge: {name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}
plugins:
  knobs:
    host: h
    OPTION
topics:
  - {topic: /t, type: std_msgs/msg/String, direction: transmit, port: 12001, codec: knobs}
"""


# --- a misspelt hook ------------------------------------------------------------------------------

def test_a_misspelt_hook_is_reported_by_plugins_and_check(site, tmp_path):
    install(site, "rosgate-transport-typo", "typo", TYPO)
    reason = f"unknown hook 'rosgate_transport' (did you mean 'rosgate_transports'?); {HOOKS}"

    listing = rosgate(site, "plugins")
    assert listing.returncode == 0, listing.stderr
    assert f"failed to load plugin 'typo' (rosgate-transport-typo): {reason}" in listing.stdout
    assert any(line.split()[:2] == ["transport", "udp"] for line in listing.stdout.splitlines())

    good = tmp_path / "good.yaml"
    good.write_text(BRINGUP.replace("knobs", "cdr").replace("    host: h\n    OPTION\n", ""))
    check = rosgate(site, "check", str(good))
    assert check.returncode == 0, check.stderr
    assert check.stderr == (f"rosgate: warning: plugin 'typo' (rosgate-transport-typo) failed to "
                            f"load: {reason}\n")

    uses_it = tmp_path / "typo.yaml"
    uses_it.write_text(good.read_text().replace("port: 12001", "port: 12001, transport: typo"))
    check = rosgate(site, "check", str(uses_it))
    assert check.returncode == 2
    assert (f"{uses_it}:5: topics[0].transport: unknown transport 'typo' (installed transports: "
            in check.stderr)
    assert f"plugin 'typo' is installed but failed to load: {reason}" in check.stderr
    assert "fix: repair or reinstall rosgate-transport-typo, or pick an installed transport" \
        in check.stderr


# --- every mistake in a plugin's options, located -------------------------------------------------

@pytest.mark.parametrize("option, line, key, message, fix", [
    ("levle: 2", 5, "plugins.knobs.levle", "unknown key 'levle' (did you mean 'level'?)",
     "valid keys are host, level, mode, colour, names, low, high"),
    ("", 3, "plugins.knobs.host", "missing required key 'host' (where the knobs are)",
     "add host: <a string> under plugins: knobs:"),
    ("level: true", 5, "plugins.knobs.level", "expected an integer 1..9, got true (a boolean)",
     "level: how hard to try (an integer, 1..9, default 3)"),
    ("level: 12", 5, "plugins.knobs.level", "expected an integer 1..9, got 12",
     "level: how hard to try (an integer, 1..9, default 3)"),
    ("mode: both", 5, "plugins.knobs.mode", "'both' is not one of push, pull",
     "mode: who starts (one of: push, pull, default push)"),
    ("colour: blue", 5, "plugins.knobs.colour", "'blue' is not one of red, green",
     "colour: colour of the log lines (a string, one of: red, green, default red)"),
    ("names: [a, 1]", 5, "plugins.knobs.names",
     "expected a list (a string each), got a list ['a', 1]",
     "names: names to leave out (a list (a string each), default [])"),
    ("low: 5\n    high: 4", 6, "plugins.knobs.high", "must not be below low (5)",
     "swap low and high"),
], ids=["unknown", "missing", "type", "range", "literal", "choices", "list", "cross-field"])
def test_check_locates_every_option_error_at_file_line_key(site, tmp_path, option, line, key,
                                                           message, fix):
    install(site, "rosgate-codec-knobs", "knobs", KNOBS)
    path = tmp_path / "bringup.yaml"
    text = BRINGUP.replace("OPTION", option)
    path.write_text(text.replace("    host: h\n", "") if key == "plugins.knobs.host" else text)
    result = rosgate(site, "check", str(path))
    assert result.returncode == 2
    assert result.stderr == f"rosgate: error: {path}:{line}: {key}: {message}\n  fix: {fix}\n"


def test_check_accepts_the_options_when_they_are_right(site, tmp_path):
    install(site, "rosgate-codec-knobs", "knobs", KNOBS)
    path = tmp_path / "bringup.yaml"
    path.write_text(BRINGUP.replace("OPTION", "names: [a, b]\n    mode: pull\n    level: 9"))
    result = rosgate(site, "check", str(path))
    assert (result.returncode, result.stderr) == (0, "")
    assert "/t -> /t  [std_msgs/msg/String] udp:12001 knobs none" in result.stdout


# --- listing --------------------------------------------------------------------------------------

def test_plugins_options_prints_each_option_in_columns():
    result = rosgate(Path("/nonexistent"), "plugins", "--options", "udp")
    assert (result.returncode, result.stderr) == (0, "")
    assert result.stdout == (
        "transport udp (rosgate-transport-udp 0.1.0), under plugins: udp:\n"
        "  OPTION          TYPE        DEFAULT  DESCRIPTION\n"
        "  receive_buffer  int         4194304  bytes of kernel receive buffer to ask for (>= 1)\n"
        "  send_buffer     int         4194304  bytes of kernel send buffer to ask for (>= 1)\n"
        "  max_frame       int | None  null     the largest datagram to send, in bytes; longer "
        "frames go in fragments. Default: the path's MTU less the IP and UDP headers (1472 on "
        "Ethernet, 65000 on loopback), 1200 where the path is not known; a value set here is an "
        "upper bound (256..65000)\n"
        "  offload         bool        true     let the kernel cut and join a frame's datagrams "
        "(UDP_SEGMENT, UDP_GRO) where it can: one system call per frame\n")


def test_plugins_options_shows_required_options_choices_and_option_less_plugins(site):
    install(site, "rosgate-codec-knobs", "knobs", KNOBS)
    lines = rosgate(site, "plugins", "--options", "knobs").stdout.splitlines()
    assert lines[0] == "codec knobs (rosgate-codec-knobs 1.0), under plugins: knobs:"
    rows = {line.split()[0]: line.split(None, 3) for line in lines[2:]}
    assert rows["host"] == ["host", "str", "required", "where the knobs are"]
    assert rows["mode"] == ["mode", "str", "push", "who starts (one of: push, pull)"]
    assert rows["names"] == ["names", "list[str]", "[]", "names to leave out"]
    assert rosgate(site, "plugins", "--options", "cdr").stdout.splitlines()[1:] == ["  no options"]


def test_plugins_options_of_an_unknown_name_is_an_error():
    result = rosgate(Path("/nonexistent"), "plugins", "--options", "nope")
    assert result.returncode == 2
    assert result.stderr.startswith("rosgate: error: plugins: no plugin is named 'nope' "
                                    "(installed: aead, bt, can, cbor, cdr, ")


def test_plugins_aligns_columns_to_the_longest_name_and_names_a_transport_of_no_kind(site):
    install(site, "rosgate-transport-long-and-rather-long-name", "long", LONG)
    install(site, "rosgate-transport-old", "old", KINDLESS)
    lines = rosgate(site, "plugins").stdout.splitlines()
    table = [line for line in lines if line.split()[0] in ("KIND", "transport", "codec", "cipher")]
    assert len(table) > 10
    # every cell starts where its column's header does
    assert len({tuple(cell.start() for cell in re.finditer(r"\S+", line)) for line in table}) == 1
    assert ["transport", "long", "rosgate-transport-long-and-rather-long-name", "1.0"] in [
        line.split() for line in table]
    assert ("failed to load plugin 'old' (rosgate-transport-old): OldTransport is no kind of "
            "link (subclass DatagramTransport, StreamTransport or BusTransport, since rosgate "
            "plugin API 2: docs/plugin-api.md)") in lines


# --- commands: rosgate <verb> from a plugin -------------------------------------------------------

HELLO = """
    import os

    from rosgate import Command, ConfigError, hookimpl

    if os.environ.get("HELLO_IMPORTED"):  # the test's witness that the module was imported
        open(os.environ["HELLO_IMPORTED"], "a").write("imported\\n")


    def arguments(parser):
        parser.add_argument("who")
        parser.add_argument("--times", type=int, default=1)


    def run(args):
        if args.who == "nobody":
            raise ConfigError("there is nobody to greet", file="hello", fix="name someone")
        for _ in range(args.times):
            print(f"hello {args.who}")
        return 3 if args.who == "three" else 0


    @hookimpl
    def rosgate_commands(register):
        register(Command("hello", "greet someone", run, arguments))
"""

BROKEN_VERB = """
    from dataclasses import dataclass

    from rosgate import Codec


    class SameCodec(Codec):
        name = "same"
        raw = True

        @dataclass(frozen=True)
        class Options:
            pass

        def encode(self, message):
            return message

        def decode(self, data):
            return data


    def rosgate_codecs(register):
        register(SameCodec)


    def rosgate_commands(register):
        raise RuntimeError("no verbs today")
"""

ZEALOUS = """
    from rosgate import Command


    def rosgate_commands(register):
        register(Command("run", "run something else", lambda args: 0))
        register(Command("hello", "a second hello", lambda args: 0))
        register(Command("Two Words", "not a word", lambda args: 0))
        register("wave")
        register(Command("wave", "wave at someone", lambda args: print("waving") or 0))
"""


def test_a_third_party_command_runs_with_its_arguments_and_exit_status(site):
    install(site, "rosgate-hello", "hello", HELLO)
    result = rosgate(site, "hello", "world", "--times", "2")
    assert (result.returncode, result.stdout, result.stderr) == (0, "hello world\nhello world\n",
                                                                 "")
    assert rosgate(site, "hello", "three").returncode == 3
    usage = rosgate(site, "hello")
    assert usage.returncode == 2
    assert "rosgate hello: error: the following arguments are required: who" in usage.stderr


def test_a_third_party_command_s_user_error_is_one_message_with_its_fix(site):
    install(site, "rosgate-hello", "hello", HELLO)
    result = rosgate(site, "hello", "nobody")
    assert (result.returncode, result.stdout) == (2, "")
    assert result.stderr == "rosgate: error: hello: there is nobody to greet\n  fix: name someone\n"


def test_help_and_plugins_list_a_plugin_s_command_with_its_distribution(site):
    install(site, "rosgate-hello", "hello", HELLO)
    help_text = rosgate(site, "--help").stdout
    assert re.search(r"\n    hello +greet someone \(rosgate-hello\)\n", help_text), help_text
    for verb in ("run", "check", "plugins", "keygen", "pubkey"):
        assert f"\n    {verb} " in help_text
    rows = [line.split() for line in rosgate(site, "plugins").stdout.splitlines()]
    assert ["command", "hello", "rosgate-hello", "1.0"] in rows
    assert ["command", "router", "rosgate-transport-zenoh", "0.1.0"] in rows


def test_rosgate_s_own_verbs_import_no_plugin_and_another_verb_imports_them(site, tmp_path):
    install(site, "rosgate-hello", "hello", HELLO)
    witness = tmp_path / "imported"
    key = tmp_path / "id.key"
    made = rosgate(site, "keygen", "identity", "--out", str(key), HELLO_IMPORTED=str(witness))
    assert made.returncode == 0, made.stderr
    assert rosgate(site, "pubkey", str(key), HELLO_IMPORTED=str(witness)).returncode == 0
    assert not witness.exists()
    assert rosgate(site, "hello", "you", HELLO_IMPORTED=str(witness)).stdout == "hello you\n"
    assert witness.read_text() == "imported\n"


def test_a_plugin_whose_command_fails_costs_only_its_verb(site, tmp_path):
    install(site, "rosgate-hello", "hello", HELLO)
    install(site, "rosgate-codec-same", "same", BROKEN_VERB)
    warning = ("rosgate: warning: plugin 'same' (rosgate-codec-same) failed to load: "
               "rosgate_commands: RuntimeError: no verbs today")

    result = rosgate(site, "hello", "world")
    assert (result.returncode, result.stdout) == (0, "hello world\n")
    assert result.stderr.startswith(warning), result.stderr
    missing = rosgate(site, "greet")
    assert missing.returncode == 2
    assert missing.stderr.startswith(warning)
    assert "rosgate: error: argument COMMAND: invalid choice: 'greet'" in missing.stderr

    listing = rosgate(site, "plugins").stdout
    assert any(line.split()[:3] == ["codec", "same", "rosgate-codec-same"]
               for line in listing.splitlines())  # its codec is kept
    path = tmp_path / "bringup.yaml"
    path.write_text(BRINGUP.replace("knobs", "same").replace("    host: h\n    OPTION\n", ""))
    check = rosgate(site, "check", str(path))
    assert check.returncode == 0, check.stderr
    assert "/t -> /t  [std_msgs/msg/String] udp:12001 same none" in check.stdout


def test_commands_that_cannot_be_registered_are_reported_and_skipped(site):
    install(site, "rosgate-hello", "hello", HELLO)
    install(site, "rosgate-zealous", "zealous", ZEALOUS)  # loaded after hello: by name
    listing = rosgate(site, "plugins").stdout.splitlines()
    failures = [line for line in listing if line.startswith("failed to load plugin 'zealous'")]
    assert [line.split(": ", 1)[1] for line in failures] == [
        "command 'run' is rosgate's own; skipped",
        "command 'hello' is already provided by rosgate-hello; skipped",
        "command name 'Two Words' is not a lower-case word (e.g. 'router')",
        "registered 'wave', which is not a rosgate.Command"]
    assert ["command", "wave", "rosgate-zealous", "1.0"] in [line.split() for line in listing]
    assert rosgate(site, "wave").stdout == "waving\n"
    assert rosgate(site, "hello", "again").stdout == "hello again\n"  # the first one's
    assert rosgate(site, "run").stderr.endswith("the following arguments are required: file\n")


def test_plugins_add_and_remove_a_command_in_process():
    import types

    from rosgate import Command
    from rosgate.plugins import Plugins

    module = types.ModuleType("waving")
    wave = Command("wave", "wave", lambda args: 0)
    module.rosgate_commands = lambda register: register(wave)  # type: ignore[attr-defined]
    plugins = Plugins()
    plugins.add(module, "waving", "rosgate-waving", "2.0")
    assert plugins.failures == []
    registration = plugins.commands["wave"]
    assert (registration.command, registration.plugin, registration.distribution,
            registration.version) == (wave, "waving", "rosgate-waving", "2.0")
    plugins.remove("waving")
    assert plugins.commands == {}
