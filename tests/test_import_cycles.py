"""tools/import_cycles.py, the check `make lint` runs on the folders of scripts (bench/, tests/,
examples/), finds a cycle wherever its imports are written and names it; the repository has
none."""

from __future__ import annotations

import subprocess
import sys
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
