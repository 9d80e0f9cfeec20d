"""What an idle bridge costs with many routes: a client and its server with 200 topics listed
one by one, beside the same 200 found by one pattern entry (``/bench/**``), in one run. A
process publishes nothing on 200 topics; once every route is up, each bridge's CPU over a
quiet window and its memory are read from /proc. Run: ``.venv/bin/python bench/idle_routes.py
[--topics 200] [--seconds 10]``."""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fleet import memory_mb
from processes import ROSGATE, cpu_seconds, free_port, next_domains, ros_env

PUBLISHERS = """
import sys, time, rclpy
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("idle_publishers")
keep = [node.create_publisher(String, f"/bench/t{i}", 10) for i in range(int(sys.argv[1]))]
print("ready", flush=True)
time.sleep(3600)
"""


def files(folder: Path, case: str, topics: int, port: int) -> tuple[Path, Path]:
    server = folder / f"{case}-server.yaml"
    # a benchmark on loopback; without identities a client's hello is its first frame, which a
    # server takes only up to max_frame_before_auth (64 kB): 200 listed entries say more
    server.write_text(f"bridge: {{name: base, role: server, server: '127.0.0.1:{port}', "
                      "insecure: true, limits: {max_frame_before_auth: 4194304}}\n")
    if case == "listed":
        entries = "".join(f"  - {{topic: /bench/t{i}, type: std_msgs/msg/String, "
                          "direction: transmit}\n" for i in range(topics))
    else:
        entries = f"  - {{topic: /bench/**, direction: transmit, max_routes: {topics}}}\n"
    client = folder / f"{case}-client.yaml"
    client.write_text(f"bridge: {{name: robot1, role: client, server: '127.0.0.1:{port}', "
                      "insecure: true}  # a benchmark on loopback\ntopics:\n" + entries)
    return server, client


def wait_line(log: Path, text: str, count: int, timeout: float) -> bool:
    """Whether ``log`` (a file a process writes) says ``text`` ``count`` times in ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log.exists() and log.read_text(errors="replace").count(text) >= count:
            return True
        time.sleep(0.2)
    return False


def start(folder: Path, name: str, command: list[str], domain: int) -> subprocess.Popen:
    """A process whose output goes to a file (a pipe nobody reads would stop it)."""
    with open(folder / f"{name}.log", "w") as out:
        return subprocess.Popen(command, env=ros_env(domain), stdout=out,
                                stderr=subprocess.STDOUT, text=True)


def case(name: str, topics: int, seconds: float, folder: Path) -> dict[str, float]:
    near, far = next_domains()
    server_file, client_file = files(folder, name, topics, free_port())
    procs = []
    try:
        procs.append(start(folder, f"{name}-publishers",
                           [sys.executable, "-c", PUBLISHERS, str(topics)], near))
        assert wait_line(folder / f"{name}-publishers.log", "ready", 1, 60)
        server = start(folder, f"{name}-server", [ROSGATE, "run", str(server_file)], far)
        client = start(folder, f"{name}-client", [ROSGATE, "run", str(client_file)], near)
        procs += [server, client]
        ready = ("): bridged", topics) if name == "patterns" else ("server 'base' up", 1)
        assert wait_line(folder / f"{name}-client.log", *ready, 120), \
            f"{name}: the routes never came up"
        time.sleep(2)  # what the routes' first seconds cost (announcements) is not idle
        before = {p.pid: cpu_seconds(p.pid) for p in (server, client)}
        time.sleep(seconds)
        used = {p.pid: cpu_seconds(p.pid) - before[p.pid] for p in (server, client)}
        return {"client_cpu": 100 * used[client.pid] / seconds,
                "server_cpu": 100 * used[server.pid] / seconds,
                "client_mb": memory_mb(client.pid)[0], "server_mb": memory_mb(server.pid)[0]}
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--topics", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        results = {name: case(name, args.topics, args.seconds, Path(folder))
                   for name in ("listed", "patterns")}
    print(f"idle bridges, {args.topics} routes, {args.seconds:g} s window (CPU % of one core, "
          "RSS MB)")
    print("| routes | client CPU | server CPU | client RSS | server RSS |")
    print("|---|---|---|---|---|")
    for name, r in results.items():
        print(f"| {args.topics} {name} | {r['client_cpu']:.1f} % | {r['server_cpu']:.1f} % | "
              f"{r['client_mb']:.0f} | {r['server_mb']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
