"""tools/import_cycles.py, the check `make lint` runs on the folders of scripts (bench/, tests/,
examples/), finds a cycle wherever its imports are written and names it; the repository has
none. And import-linter, which checks the packages, is told of every package there is."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECK = ROOT / "tools" / "import_cycles.py"


def check(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(CHECK), str(root)], capture_output=True,
                          text=True, timeout=60)


def test_a_cycle_through_a_function_and_type_checking_is_named_file_by_file(tmp_path):
    scripts = tmp_path / "bench"
    scripts.mkdir()
    (scripts / "bench.py").write_text("import os\n\ndef draw():\n    import plots\n")
    (scripts / "plots.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from results import Row\n")
    (scripts / "results.py").write_text("from bench import log\n")
    (scripts / "alone.py").write_text("import results\n")
    package = tmp_path / "src" / "pkg"  # a package's modules are import-linter's part
    package.mkdir(parents=True)
    (package / "a.py").write_text("import b\n")
    (package / "b.py").write_text("import a\n")
    found = check(tmp_path)
    assert found.returncode == 1, found
    assert found.stdout.splitlines() == [
        "bench/: import cycle bench.py -> plots.py -> results.py -> bench.py: move what both "
        "need to a module both import"]
    (scripts / "results.py").write_text("import logging\n")
    assert check(tmp_path).returncode == 0


def test_the_repository_has_no_cycle_among_its_scripts():
    found = check(ROOT)
    assert (found.returncode, found.stdout) == (0, "")


def packages() -> set[str]:
    """The import name of every distribution in the repository."""
    sources = [ROOT / "core" / "src", *ROOT.glob("*/*/src"), *ROOT.glob("tests/thirdparty/*/src")]
    return {p.name for src in sources for p in src.iterdir()
            if (p / "__init__.py").exists()}


def test_import_linter_checks_every_package_and_every_plugin_against_the_public_api():
    linter = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    assert set(linter["root_packages"]) == packages(), "add the new package to root_packages"
    api = next(c for c in linter["contracts"] if "only the public API" in c["name"])
    # the core itself and the docs generator (it reads the core's schema) are no plugins
    assert set(api["source_modules"]) == packages() - {"rosgate", "rosgate_docgen"}
