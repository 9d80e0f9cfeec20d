"""Meta-tests, in the manner of datasette's: every plugin in this repository runs the plugin
kit's conformance suite of its kind in its own tests, and declares its options, each with a doc,
so a new plugin cannot land without."""

from __future__ import annotations

import importlib.util
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

from rosgate.bus import BusTransport
from rosgate.options import declaration_problem, declared
from rosgate.plugins import Plugins

ROOT = Path(__file__).resolve().parent.parent
SUITES = {"transport": "TransportConformance", "codec": "CodecConformance",
          "cipher": "CipherConformance", "transform": "TransformConformance",
          "packetizer": "PacketizerConformance", "service_framing": "ServiceFramingConformance"}


def folders_of_tests() -> dict[str, Path]:
    """Distribution name -> its tests folder, for every distribution in the repository."""
    folders = {}
    # examples/ too: the CAN link there is written from outside the core, yet ships with it
    for pyproject in [ROOT / "core" / "pyproject.toml", *ROOT.glob("plugins/*/pyproject.toml"),
                      *ROOT.glob("tests/thirdparty/*/pyproject.toml"),
                      *ROOT.glob("examples/*/pyproject.toml")]:
        name = tomllib.loads(pyproject.read_text())["project"]["name"]
        folders[name] = pyproject.parent / "tests"
    return folders


def suite_of(kind: str, cls: type) -> str:
    """A bus is a transport with a suite of its own."""
    return "BusConformance" if issubclass(cls, BusTransport) else SUITES[kind]


REGISTRATIONS = [r for r in Plugins.discover().all() if r.distribution in folders_of_tests()]
# monitors have no conformance suite in the kit yet: their tests run a real bridge
IN_TREE = sorted((r.kind, r.name, r.cls.__name__, r.distribution, suite_of(r.kind, r.cls))
                 for r in REGISTRATIONS if r.kind in SUITES)


def test_every_in_tree_plugin_is_found():
    assert {(kind, name) for kind, name, _, _, _ in IN_TREE} >= {
        ("transport", "udp"), ("transport", "tcp"), ("transport", "unixdgram"),
        ("transport", "can"), ("transport", "bt"), ("transport", "zenoh"),
        ("codec", "cdr"), ("codec", "msgpack"), ("codec", "cbor"), ("codec", "json"),
        ("cipher", "none"), ("cipher", "fernet"), ("cipher", "nacl"),
        ("transform", "zstd"), ("packetizer", "fragments"), ("packetizer", "compact"),
        ("packetizer", "fec"),
        ("packetizer", "retransmit")}


@pytest.mark.parametrize("kind, name, cls, distribution, suite", IN_TREE,
                         ids=[f"{kind}-{name}" for kind, name, _, _, _ in IN_TREE])
def test_runs_the_conformance_suite_of_its_kind(kind, name, cls, distribution, suite):
    sources = [path.read_text() for path in folders_of_tests()[distribution].glob("test_*.py")]
    assert any(f"({suite}):" in text and f" = {cls}\n" in text for text in sources), (
        f"no test class of {distribution} subclasses rosgate_testing.{suite} with "
        f"{kind} = {cls}")


@pytest.mark.parametrize("registration", REGISTRATIONS,
                         ids=[f"{r.kind}-{r.name}" for r in REGISTRATIONS])
def test_declares_its_options_each_with_a_doc(registration):
    cls = registration.cls
    options = declared(cls)
    assert options is not None, (
        f"{cls.__name__} declares no Options (a frozen dataclass; an empty one if it takes none)")
    assert declaration_problem(cls) is None
    for o in options:
        assert o.doc, (f"{cls.__name__}.Options.{o.name} has no doc: make it with "
                       "rosgate.option(default, doc)")


def test_the_kit_is_a_distribution_of_its_own_and_no_plugin():
    """Plugin authors' tests install rosgate-testing; a bridge installs rosgate without it."""
    assert importlib.util.find_spec("rosgate.testing") is None
    kit = metadata.distribution("rosgate-testing")
    assert [ep.group for ep in kit.entry_points] == ["pytest11"]  # not in the group rosgate


def test_the_libraries_are_no_plugins_and_every_plugin_folder_holds_one():
    """libs/ holds what plugins and their tests use; plugins/ holds only plugins."""
    for pyproject in ROOT.glob("libs/*/pyproject.toml"):
        project = tomllib.loads(pyproject.read_text())["project"]
        assert "rosgate" not in project.get("entry-points", {}), pyproject.parent.name
    for pyproject in ROOT.glob("plugins/*/pyproject.toml"):
        project = tomllib.loads(pyproject.read_text())["project"]
        assert "rosgate" in project.get("entry-points", {}), (
            f"{pyproject.parent.name} registers no plugin: a library goes to libs/")
