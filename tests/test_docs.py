"""The documentation a newcomer reads: a short README whose quickstart comes first and works,
links that lead somewhere, and pages that speak of features, not of how they were developed."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
import yaml
from conftest import ROSGATE

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_LINES = 300
QUICKSTART_WITHIN = 60

FENCE = re.compile(r"^```(\w*)\s*$")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
INLINE_CODE = re.compile(r"`[^`\n]*`")
HISTORY = re.compile(r"\bissues?\s*#?\s*\d+|\bwave\s+\d+", re.IGNORECASE)


def blocks(path: Path) -> list[tuple[str, int, int, str]]:
    """The fenced blocks of a page: (language, first line, last line, text), lines from 1."""
    found, language, start, body = [], None, 0, []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        fence = FENCE.match(line)
        if fence and language is None:
            language, start, body = fence.group(1), number, []
        elif line.strip() == "```" and language is not None:
            found.append((language, start, number, "\n".join(body)))
            language = None
        elif language is not None:
            body.append(line)
    assert language is None, f"{path.name}:{start}: a code block is never closed"
    return found


def prose(path: Path, code: bool = False) -> list[tuple[int, str]]:
    """The lines outside fenced blocks, with inline code taken out (what links live in) or, with
    ``code``, only its backticks (what headings' anchors are made of)."""
    inside, lines = False, []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.startswith("```"):
            inside = not inside
        elif not inside:
            lines.append((number, line.replace("`", "") if code else INLINE_CODE.sub("", line)))
    return lines


def anchors(path: Path) -> set[str]:
    """GitHub's anchors for a page's headings: lower case, punctuation dropped, spaces to -."""
    seen: dict[str, int] = {}
    for _, line in prose(path, code=True):
        heading = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            slug = re.sub(r"[^\w\- ]", "", heading.group(1).lower()).replace(" ", "-")
            seen[slug] = seen.get(slug, -1) + 1
            if seen[slug]:
                seen[f"{slug}-{seen[slug]}"] = 0
    return set(seen)


def test_the_readme_is_short():
    lines = len(README.read_text().splitlines())
    assert lines <= README_MAX_LINES, (
        f"README.md has {lines} lines; keep it to {README_MAX_LINES} and move reference to docs/")


def quickstart() -> tuple[list[tuple[str, int, int, str]], list[tuple[str, int, int, str]]]:
    """The quickstart: the first two sh blocks (keys, then check and run) and the first two yaml
    blocks (the client's file and the server's) of the README."""
    found = blocks(README)
    shells = [block for block in found if block[0] == "sh"][:2]
    files = [block for block in found if block[0] == "yaml"][:2]
    assert len(shells) == 2 and len(files) == 2, (
        "the README's quickstart has two sh blocks (keys; check and run) and two yaml blocks")
    return shells, files


def test_the_quickstart_comes_first():
    shells, files = quickstart()
    for language, first, last, _ in [*shells, *files]:
        assert last <= QUICKSTART_WITHIN, (
            f"README.md:{first}: the quickstart's {language} block ends at line {last}; "
            f"it belongs within the first {QUICKSTART_WITHIN} lines")
    keys, run = shells[0][3], shells[1][3]
    assert keys.count("rosgate keygen identity") == 2, keys
    assert "rosgate check" in run and "rosgate run" in run, run
    client, server = files[0][3], files[1][3]
    assert "role: client" in client and "topics:" in client, client
    assert "role: server" in server and "clients:" in server, server


def test_the_quickstart_works(tmp_path):
    """The quickstart's own commands and files, as written, with the keys its keygen prints."""
    shells, files = quickstart()
    keys: dict[str, str] = {}
    for line in shells[0][3].splitlines():
        made = re.match(r"rosgate (keygen identity .*?)\s*#.*\bprints (\w+)", line)
        if made:
            result = subprocess.run([ROSGATE, *made.group(1).split()], cwd=tmp_path,
                                    capture_output=True, text=True, timeout=60)
            assert result.returncode == 0, result.stderr
            keys[made.group(2)] = result.stdout.strip()
    assert len(keys) == 2, f"the keygen lines say which key each prints: {shells[0][3]}"
    for _, _, _, text in files:
        for placeholder, key in keys.items():
            text = text.replace(placeholder, key)
        name = re.search(r"name: (\w+)", text)
        assert name, text
        (tmp_path / f"{name.group(1)}.yaml").write_text(text + "\n")
    checks = re.findall(r"rosgate check (\S+)", shells[1][3])
    assert len(checks) == 2, shells[1][3]
    outputs = []
    for file in checks:
        assert (tmp_path / file).exists(), f"{file} is checked, but no quickstart file is named so"
        result = subprocess.run([ROSGATE, "check", file], cwd=tmp_path, capture_output=True,
                                text=True, timeout=60)
        assert result.returncode == 0, (file, result.stdout, result.stderr)
        assert "Traceback" not in result.stderr
        outputs.append(result.stdout)
    assert "ok (server 'base', 0 topic(s), 1 client(s))" in "".join(outputs)
    assert "  robot1 may send topic /chatter  [any type]  ciphers any, main port only\n" \
        in "".join(outputs)
    assert "ok (client 'robot1', 1 topic(s))" in "".join(outputs)
    assert "/chatter -> /chatter  [std_msgs/msg/String] udp cdr aead" in "".join(outputs)


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(ROOT).as_posix())
def test_relative_links_lead_somewhere(page):
    broken = []
    for number, line in prose(page):
        for target in LINK.findall(line):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
                continue
            file, _, anchor = target.partition("#")
            resolved = (page.parent / file).resolve() if file else page
            if not resolved.exists():
                broken.append(f"{page.name}:{number}: {target}: no file {file}")
            elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
                broken.append(f"{page.name}:{number}: {target}: no heading #{anchor} there")
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(ROOT).as_posix())
def test_pages_speak_of_features_not_issues(page):
    found = [f"{page.name}:{number}: {match.group(0)!r}"
             for number, line in enumerate(page.read_text().splitlines(), 1)
             for match in HISTORY.finditer(line)]
    assert not found, "say what the feature is, not which issue brought it:\n" + "\n".join(found)


def test_the_link_checker_sees_links_and_anchors(tmp_path):
    """The checks above would pass on anything if they found no links: they do find them."""
    page = tmp_path / "page.md"
    page.write_text("# A server's clients\n\n## Wi-Fi and radio links\n\n## The `bt` link\n\n"
                    "[x](other.md#top) `[not](a-link.md)` ![p](../img.png)\n"
                    "```\n[inside](code.md)\n```\n")
    assert anchors(page) == {"a-servers-clients", "wi-fi-and-radio-links", "the-bt-link"}
    links = [target for _, line in prose(page) for target in LINK.findall(line)]
    assert links == ["other.md#top", "../img.png"]
    assert HISTORY.search("the attacks of issue 10") and HISTORY.search("Issue #9")
    assert not HISTORY.search("see the issue tracker")


def test_every_command_is_in_the_commands_page():
    """Every verb `rosgate --help` lists on this machine (the core's and the installed plugins')
    has a row of its own in docs/commands.md."""
    listing = subprocess.run([ROSGATE, "--help"], capture_output=True, text=True, timeout=60,
                             check=True).stdout
    verbs = re.findall(r"^    (\w+)\s", listing, re.MULTILINE)
    assert {"run", "check", "top", "router", "certs", "convert"} <= set(verbs)
    rows = (ROOT / "docs" / "commands.md").read_text()
    missing = [verb for verb in verbs if f"| `rosgate {verb}" not in rows]
    assert not missing, f"docs/commands.md has no row for: {missing}"


def test_the_readme_s_numbers_come_from_the_pages_that_measured_them():
    """The README quotes the benchmark page, not numbers of its own; and it says the same time
    for make test as the contributing page."""
    readme = " ".join(README.read_text().split())
    bench = " ".join((ROOT / "docs" / "benchmark.md").read_text().split())
    quoted = re.findall(r"(\d[\d,]*) msg/s", readme) + re.findall(r"(\d[\d,]*) reliable", readme)
    assert quoted, "the README quotes the benchmark's rate"
    for number in quoted:
        assert number in bench, f"README quotes {number} msg/s, which docs/benchmark.md does not"
    for ratio in re.findall(r"(0\.\d+)x bare", readme):
        assert f"{ratio}x" in bench, f"README quotes {ratio}x, which docs/benchmark.md does not"
    minutes = {page.name: re.findall(r"about (\d+) min", " ".join(page.read_text().split()))
               for page in (README, ROOT / "docs" / "contributing.md")}
    assert len({tuple(m) for m in minutes.values()}) == 1 and all(minutes.values()), minutes


def test_the_readme_names_only_roles_a_file_can_say():
    """`role:` takes client, server or peer: the README calls nothing else a role."""
    from rosgate.config.schema import Role

    said = re.findall(r"`role: (\w+)`", README.read_text())
    assert said and set(said) <= {str(r) for r in Role}, said
    headings = re.findall(r"^## (.*roles?.*)$", README.read_text(), re.MULTILINE | re.IGNORECASE)
    assert all("three" not in h.lower() for h in headings), headings


def test_the_plugin_guide_shows_what_plugins_options_prints():
    """The guide's sample of `rosgate plugins --options udp` is the command's own output."""
    page = (ROOT / "docs" / "plugins.md").read_text()
    shown = page.split("`rosgate plugins --options NAME` prints what a plugin declares:")[1]
    shown = shown.split("```\n", 2)[1]
    printed = subprocess.run([ROSGATE, "plugins", "--options", "udp"], capture_output=True,
                             text=True, timeout=60, check=True).stdout
    assert shown == printed


def whole_files() -> list[tuple[str, int, str]]:
    """The yaml blocks of the pages that are a whole bringup file (a bridge with a role)."""
    found = []
    for page in PAGES:
        for language, first, _, text in blocks(page):
            try:
                data = yaml.safe_load(text) if language == "yaml" else None
            except yaml.YAMLError:  # a fragment written for reading
                continue
            bridge = data.get("bridge") if isinstance(data, dict) else None
            if isinstance(bridge, dict) and "role" in bridge:
                found.append((page.relative_to(ROOT).as_posix(), first, text))
    return found


@pytest.mark.parametrize("page, line, text", whole_files(), ids=lambda v: str(v)[:40])
def test_every_whole_file_in_the_docs_passes_check_or_says_why_it_is_insecure(page, line, text,
                                                                              tmp_path):
    """As a reader would run it, with its keys made: ``rosgate check`` accepts it without
    ``insecure: true``, or the block says ``insecure: true`` with a comment saying why."""
    from rosgate import identity

    data = yaml.safe_load(text)
    bridge = data["bridge"]
    if bridge.get("insecure"):
        assert re.search(r"#\s*\w", text), f"{page}:{line}: say why it is insecure: true"
    public = identity.encode(identity.public_of(identity.generate()))  # placeholders' stand-in
    if "identity" in bridge:
        identity.write_private(tmp_path / bridge["identity"], identity.generate())
    for key in ("server_key", "peer_key"):
        if key in bridge:
            bridge[key] = public
    for client in (data.get("clients") or {}).values():
        client["key"] = public
    for name, options in (data.get("plugins") or {}).items():  # a cipher's key file, made
        if isinstance(options, dict) and "key_file" in options:
            made = subprocess.run([ROSGATE, "keygen", name, "--out", options["key_file"]],
                                  cwd=tmp_path, capture_output=True, text=True, timeout=60)
            assert made.returncode == 0, made.stderr
    path = tmp_path / "bringup.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    result = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                            timeout=60)
    if "AF_BLUETOOTH" in result.stderr:
        pytest.skip("this Python has no Bluetooth sockets")
    assert result.returncode == 0, f"{page}:{line}:\n{result.stderr}"
    assert ("INSECURE" in result.stderr) == bool(bridge.get("insecure")), result.stderr


def test_the_docs_hold_whole_files_of_every_role_and_on_zenoh():
    """The test above sees the files it is meant to."""
    texts = [text for _, _, text in whole_files()]
    for role in ("client", "server", "peer"):
        assert any(f"role: {role}" in text for text in texts), role
    assert sum("transport: zenoh" in text for text in texts) >= 3
