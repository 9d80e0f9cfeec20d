"""The README's install line, as written, from the wheels `make wheels` builds: into a bare
virtual environment (nothing of this repository's .venv), then the quickstart from it — `check`
on both files and `/chatter` across two bridges of that environment."""

from __future__ import annotations

import re
import shlex
import subprocess
import venv
from pathlib import Path

import pytest
from conftest import free_port, warm_up
from test_docs import README, quickstart

from rosgate.rostypes import resolve_type

ROOT = Path(__file__).resolve().parents[1]
# building 28 wheels and installing rclpy with them takes minutes on a busy machine
pytestmark = pytest.mark.timeout(900)


def install_line() -> list[str]:
    """The quickstart's pip line, split into its words after `pip install`."""
    keys = quickstart()[0][0][3]
    line = next(line for line in keys.splitlines() if line.startswith("pip install"))
    assert "--find-links dist" in line, f"{README.name}: the install line installs from dist/"
    return shlex.split(line.split("#")[0])[2:]


@pytest.fixture(scope="module")
def bare(tmp_path_factory) -> Path:
    """A virtual environment with what the README's install line installs, and nothing else."""
    folder = tmp_path_factory.mktemp("install")
    built = subprocess.run(["make", "-s", "wheels", f"DIST={folder / 'dist'}"], cwd=ROOT,
                           capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stdout + built.stderr
    venv.EnvBuilder(with_pip=True).create(folder / "venv")
    python = folder / "venv" / "bin" / "python"
    words = [word.replace("dist", str(folder / "dist")) if word == "dist" else word
             for word in install_line()]
    installed = subprocess.run([str(python), "-m", "pip", "install", "--quiet", *words],
                               capture_output=True, text=True, timeout=900)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    return folder / "venv" / "bin"


# one test of both, the install line's packages and the quickstart run from them: the fixture,
# wheels built and installed (a minute), is made once per worker that runs a test of it
def test_the_install_line_installs_what_it_names_and_the_quickstart_runs_from_it(
        bare, tmp_path, domain, bridge, ros_side):
    installs_what_it_names_and_nothing_of_the_clone(bare)
    the_quickstart_runs_from_the_installed_wheels(bare, tmp_path, domain, bridge, ros_side)


def installs_what_it_names_and_nothing_of_the_clone(bare: Path) -> None:
    listed = subprocess.run([str(bare / "python"), "-m", "pip", "list", "--format=freeze"],
                            capture_output=True, text=True, timeout=120, check=True).stdout
    names = {line.split("==")[0].lower().replace("_", "-") for line in listed.splitlines()}
    for word in install_line():
        name = re.sub(r"\[.*\]", "", word).strip('"').lower()
        if not name.startswith("-") and name != "dist":
            assert name in names, (name, sorted(names))
    assert "rosgate-testing" not in names and "rosgate-emulator" not in names
    where = subprocess.run([str(bare / "python"), "-c", "import rosgate; print(rosgate.__file__)"],
                           capture_output=True, text=True, timeout=60, check=True).stdout
    assert where.startswith(str(bare.parent)), where  # the wheel's copy, not the clone's


def the_quickstart_runs_from_the_installed_wheels(bare: Path, tmp_path: Path, domain, bridge,
                                                  ros_side) -> None:
    rosgate = str(bare / "rosgate")
    keys = {}
    for side, placeholder in (("base", "BASE_KEY"), ("robot1", "ROBOT1_KEY")):
        made = subprocess.run([rosgate, "keygen", "identity", "--out", f"{side}.key"],
                              cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert made.returncode == 0, made.stderr
        keys[placeholder] = made.stdout.strip()
    port = free_port()
    for _, _, _, text in quickstart()[1]:
        for placeholder, key in keys.items():
            text = text.replace(placeholder, key)
        text = re.sub(r"server: [\d.]+:12000", f"server: 127.0.0.1:{port}", text)
        text = re.sub(r"(identity: )(\w+\.key)", lambda m: f"{m[1]}{tmp_path / m[2]}", text)
        name = re.search(r"name: (\w+)", text)
        assert name, text
        (tmp_path / f"{name[1]}.yaml").write_text(text + "\n")
    for side in ("base", "robot1"):
        checked = subprocess.run([rosgate, "check", f"{side}.yaml"], cwd=tmp_path,
                                 capture_output=True, text=True, timeout=60)
        assert checked.returncode == 0, checked.stdout + checked.stderr
    robot, base = domain(), domain()
    bridge(tmp_path / "base.yaml", base, rosgate=rosgate)
    bridge(tmp_path / "robot1.yaml", robot, rosgate=rosgate)
    string = resolve_type("std_msgs/msg/String")
    talker = ros_side(robot, "talker").ros.publisher(string, "/chatter", 10)
    inbox = ros_side(base, "listener").listen("/chatter", string)
    warm_up(talker, inbox, string(data="hello from the wheels"), timeout=60)
    assert inbox.items[0].data == "hello from the wheels"
