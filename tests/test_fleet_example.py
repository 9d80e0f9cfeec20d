"""examples/fleet: its files pass ``rosgate check``, and run.sh — the docker-compose.yml fleet as
plain processes — makes the fleet's certificates, starts the router with mutual TLS and access
control, and carries a robot's odometry to the base and the base's commands to a robot."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import ROSGATE, free_port
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from test_cli import rosgate

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "fleet"


@pytest.mark.parametrize("name", ["robot1", "robot2", "base"])
def test_the_example_files_pass_check(name):
    result = rosgate("check", str(EXAMPLE / f"{name}.yaml"))
    assert result.returncode == 0, result.stderr


def test_run_sh_brings_up_the_fleet(tmp_path, domain, ros_side):
    folder = tmp_path / "fleet"
    shutil.copytree(EXAMPLE, folder, ignore=shutil.ignore_patterns("certs"))  # run.sh makes them
    port = str(free_port())  # 7447 may be taken on a shared machine
    for path in [*folder.glob("*.yaml"), folder / "run.sh"]:
        path.write_text(path.read_text().replace("7447", port))
    # the CA and the router's certificate already there: run.sh makes only the missing ones
    made = subprocess.run([ROSGATE, "certs", "--out", str(folder / "certs"), "router"],
                          capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    before = {name: (folder / "certs" / f"{name}.pem").read_bytes() for name in ("ca", "router")}
    d = {"robot1": domain(), "robot2": domain(), "base": domain()}
    env = dict(os.environ, ROBOT1_DOMAIN=str(d["robot1"]), ROBOT2_DOMAIN=str(d["robot2"]),
               BASE_DOMAIN=str(d["base"]), PYTHONUNBUFFERED="1")
    fleet = subprocess.Popen(["bash", str(folder / "run.sh"), ROSGATE], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             start_new_session=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(fleet.stdout), daemon=True).start()
    try:
        base, robot1, robot2 = (ros_side(d[n], n) for n in ("base", "robot1", "robot2"))
        odom, cmd = base.listen("/robot1/odom", Odometry), robot2.listen("/cmd_vel", Twist)
        odom_out, cmd_out = robot1.publisher("/odom", Odometry), base.publisher("/robot2/cmd_vel",
                                                                               Twist)
        deadline = time.monotonic() + 60
        while not (odom.items and cmd.items):
            assert time.monotonic() < deadline, "\n".join(lines)
            odom_out.publish(Odometry(child_frame_id="robot1_base"))
            cmd_out.publish(Twist())
            time.sleep(0.2)
        assert odom.items[0].child_frame_id == "robot1_base"
    finally:
        os.killpg(fleet.pid, signal.SIGINT)
        try:
            fleet.wait(30)
        except subprocess.TimeoutExpired:
            left = subprocess.run(["ps", "-ww", "-o", "pid,stat,etime,args", "-g",
                                   str(fleet.pid)], capture_output=True, text=True).stdout
            for pid in [row.split()[0] for row in left.splitlines()[1:] if "python" in row]:
                left += subprocess.run([str(Path(sys.executable).with_name("py-spy")), "dump",
                                        "--pid", pid], capture_output=True, text=True).stdout
            os.killpg(fleet.pid, signal.SIGKILL)
            raise AssertionError(f"still running 30 s after SIGINT:\n{left}\n"
                                 + "\n".join(lines[-40:])) from None
    text = "\n".join(lines)
    assert "Traceback" not in text
    assert text.count("fleet: publishing /robot1/odom for robot robot1") == 1
    for name in ("robot1", "robot2", "base"):  # made by run.sh's rosgate certs, with that CA
        assert f"wrote certs/{name}.pem" in text and (folder / "certs" / f"{name}.pem").is_file()
        assert (folder / "certs" / f"{name}.key").stat().st_mode & 0o077 == 0
    for name, pem in before.items():  # kept as they were
        assert f"wrote certs/{name}.pem" not in text
        assert (folder / "certs" / f"{name}.pem").read_bytes() == pem
    assert "listening on tls/127.0.0.1:" in text
    assert "without TLS" not in text and "INSECURE" not in text
    for robot in ("robot1", "robot2"):  # each robot's token passed the router's access control
        assert f"fleet: robot {robot} joined (its liveliness token)" in text
