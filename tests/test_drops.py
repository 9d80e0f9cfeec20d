"""Drop reasons are one enumeration: every reason counted in the code is a member (or a reason a
plugin declared, with its sentence), docs/operators.md's table is generated from it, and a bare
string where a reason is counted fails here."""

from __future__ import annotations

import ast
import importlib
import inspect
import re
from collections import Counter
from pathlib import Path

import pytest
from rosgate_docgen import BEGIN, DROPS_COMMAND, END, drop_reasons, render

from rosgate import drops
from rosgate.drops import Drop, PluginDrop, declare

ROOT = Path(__file__).resolve().parents[1]
OPERATORS = ROOT / "docs" / "operators.md"
SOURCES = [ROOT / "core" / "src", *sorted(ROOT.glob("plugins/*/src")),
           *sorted(ROOT.glob("libs/*/src"))]
#: calls that count a drop, whatever their receiver: their arguments must not be bare strings
COUNTING = re.compile(r"(^|\.)(drop|link_drop|_drop|on_lost|lost|_give_up|_refused|refuse_"
                      r"connection|fail|fail_all|discard|on_error)$|dropped\.append$")
REASON_LIKE = re.compile(r"^[a-z]+(_[a-z0-9]+)+$|^[a-z]+$")


def bare_reasons(source: str) -> list[tuple[int, str]]:
    """(line, text) of each string a drop-counting call gets where a reason goes."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call) or not COUNTING.search(ast.unparse(node.func)):
            continue
        args = [a for arg in node.args
                for a in (arg.elts if isinstance(arg, ast.Tuple) else [arg])]
        args += [arg.orelse for arg in node.args if isinstance(arg, ast.IfExp)]
        args += [arg.body for arg in node.args if isinstance(arg, ast.IfExp)]
        for arg in args:
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str) \
                    and REASON_LIKE.match(arg.value) and arg.value in _REASONS:
                found.append((arg.lineno, arg.value))
            if isinstance(arg, ast.JoinedStr) and re.search(r"_[a-z]+'$", ast.unparse(arg)):
                found.append((arg.lineno, ast.unparse(arg)))
    return found


#: the plugin modules that declare reasons of their own, and the page that explains them
PLUGIN_PAGES = {"rosgate_mcu_cvra.calls": "microcontrollers.md",
                "rosgate_transport_zenoh.rmw_dialect": "fleets.md"}


def _plugin_reasons() -> list[PluginDrop]:
    for module in PLUGIN_PAGES:
        importlib.import_module(module)  # declares its reasons
    return drops.declared()


_REASONS = {*Drop, *_plugin_reasons()}


def _python_files() -> list[Path]:
    return [p for src in SOURCES for p in sorted(src.rglob("*.py"))]


def test_no_drop_is_counted_by_a_bare_string():
    found = [f"{path.relative_to(ROOT)}:{line}: {text}" for path in _python_files()
             for line, text in bare_reasons(path.read_text(encoding="utf-8"))]
    assert found == []


@pytest.mark.parametrize("snippet", [
    'route.drop("too_late", "waited")',
    'self.router.link_drop(link, "bad_control", f"from {source}")',
    'self.on_lost(None, "bad_fragment")',
    'self.dropped.append((message.sender, "queue_full", "full"))',
    'sender.drop("link_down" if closed else "send_error", detail)',
    'self._give_up(source, sender, "fragment_lost")',
    'self.on_error("bad_crc", "CRC")',
    'self.link_drop(link, f"{exc}_frame", detail)',
    'route.drop(f"{exc}_frame", f"{len(frame)} bytes")',
])
def test_the_check_finds_a_bare_string(snippet):
    assert len(bare_reasons(snippet)) >= 1


def test_the_check_lets_members_and_details_through():
    assert bare_reasons('route.drop(Drop.TOO_LATE, "too late: waited")\n'
                        'self.on_lost(None, Drop.BAD_FRAGMENT)\n'
                        'log.warning("stale")\n') == []


def test_every_member_has_a_sentence_and_is_counted_somewhere():
    code = "\n".join(p.read_text(encoding="utf-8") for p in _python_files()
                     if p.name != "drops.py")
    for reason in Drop:
        assert reason.doc and not reason.doc.endswith("."), reason
        assert f"Drop.{reason.name}" in code, f"{reason} is never counted: remove it"


def test_members_are_the_strings_counters_and_status_show():
    counted: Counter = Counter()
    counted[Drop.TOO_LATE] += 2
    assert counted == {"too_late": 2}
    assert f"{Drop.QUEUE_FULL}={counted[Drop.QUEUE_FULL]}" == "queue_full=0"
    assert Drop("type_mismatch") is Drop.TYPE_MISMATCH
    assert repr(dict(counted)) == "{'too_late': 2}"


def test_the_table_in_operators_md_is_up_to_date():
    page = OPERATORS.read_text(encoding="utf-8")
    assert render(page, drop_reasons, DROPS_COMMAND) == page, \
        f"docs/operators.md is stale: run {DROPS_COMMAND}"
    for reason in Drop:
        assert f"| `{reason}` | {reason.doc} |" in page


def test_the_table_check_fails_when_a_row_is_missing():
    page = OPERATORS.read_text(encoding="utf-8")
    stale = page.replace(f"| `{Drop.TOO_LATE}` | {Drop.TOO_LATE.doc} |\n", "")
    assert stale != page and render(stale, drop_reasons, DROPS_COMMAND) == page
    begin = BEGIN.format(command=DROPS_COMMAND)
    assert page.count(begin) == 1 and page.rstrip().endswith(END)


def test_every_reason_a_plugin_declares_is_on_its_page():
    declared = _plugin_reasons()
    assert {"bad_crc", "too_long", "no_answer", "connect_failed", "bad_attachment"} <= \
        set(declared)
    for module, name in PLUGIN_PAGES.items():
        page = (ROOT / "docs" / name).read_text(encoding="utf-8")
        source = inspect.getsource(importlib.import_module(module))
        own = [reason for reason in declared if f'declare("{reason}"' in source]
        assert own, f"{module} declares no reason"
        for reason in own:
            assert reason.doc
            assert f"`{reason}`" in page, f"{reason} ({reason.doc}) is not in {name}"


def test_declare_gives_one_reason_per_name_and_refuses_the_cores():
    first = declare("test_only_reason", "a reason only this test counts")
    assert isinstance(first, PluginDrop) and first == "test_only_reason"
    assert first.doc == "a reason only this test counts"
    assert declare("test_only_reason", "a reason only this test counts") is first
    with pytest.raises(ValueError, match="declared already"):
        declare("test_only_reason", "another sentence")
    with pytest.raises(ValueError, match="is the core's"):
        declare("too_late", "late")
