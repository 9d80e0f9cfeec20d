"""`make demo`: two rosgate bridges on loopback, a talker on one side and a listener on the other.

The robot side (ROS domain 201) and the base-station side (domain 202) cannot see each other
over DDS; everything the listener prints came through the bridge: /chatter as msgpack over UDP,
/cmd_vel as Fernet-encrypted CDR over the TCP main line the other way. Exits by itself.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
ROSGATE = str(Path(sys.executable).with_name("rosgate"))
ROBOT, BASE = 201, 202
PORT = 23400
COUNT = 10

SERVER = f"""\
bridge:
  name: base
  role: server
  server: 127.0.0.1:{PORT}
plugins:
  fernet: {{key_file: secret.key}}
"""

CLIENT = f"""\
bridge:
  name: robot1
  role: client
  server: 127.0.0.1:{PORT}
plugins:
  fernet: {{key_file: secret.key}}
topics:
  - topic: /chatter                 # robot -> base, MessagePack over UDP
    type: std_msgs/msg/String
    direction: transmit
    remote: /robot1/chatter
    transport: udp
    codec: msgpack
  - topic: /cmd_vel                 # base -> robot, encrypted, on the TCP main line
    type: geometry_msgs/msg/Twist
    direction: receive
    remote: /robot1/cmd_vel
    transport: tcp
    cipher: fernet
"""


def start(config: Path, domain: int) -> subprocess.Popen:
    proc = subprocess.Popen([ROSGATE, "run", str(config)], stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, ROS_DOMAIN_ID=str(domain)))
    ready = threading.Event()

    def relay() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            print(f"  [{config.stem}] {line.rstrip()}", flush=True)
            if "running as" in line:
                ready.set()
        ready.set()

    threading.Thread(target=relay, daemon=True).start()
    if not ready.wait(30) or proc.poll() is not None:
        sys.exit(f"bridge {config.stem} did not start")
    return proc


def main() -> int:
    from geometry_msgs.msg import Twist
    from std_msgs.msg import String

    from rosgate.ros import RosNode

    work = Path(tempfile.mkdtemp(prefix="rosgate-demo-"))
    subprocess.run([ROSGATE, "keygen", "fernet", "--out", str(work / "secret.key")], check=True)
    (work / "server.yaml").write_text(SERVER)
    (work / "client.yaml").write_text(CLIENT)
    print(f"configs in {work}\n--- client.yaml ---\n{CLIENT}")
    bridges = [start(work / "server.yaml", BASE), start(work / "client.yaml", ROBOT)]

    robot, base = RosNode("demo_robot", ROBOT), RosNode("demo_base", BASE)
    heard, commanded = threading.Event(), threading.Event()
    received: list[str] = []

    def on_chatter(msg: String) -> None:
        print(f"base heard on /robot1/chatter:  {msg.data!r}", flush=True)
        received.append(msg.data)
        if len(received) >= COUNT:
            heard.set()

    def on_cmd(msg: Twist) -> None:
        print(f"robot got on /cmd_vel:          linear.x={msg.linear.x} angular.z={msg.angular.z}",
              flush=True)
        commanded.set()

    base.subscribe(String, "/robot1/chatter", 10, on_chatter, raw=False)
    robot.subscribe(Twist, "/cmd_vel", 10, on_cmd, raw=False)
    chatter = robot.publisher(String, "/chatter", 10)
    cmd = base.publisher(Twist, "/robot1/cmd_vel", 10)

    deadline = time.monotonic() + 30
    i = 0
    while not (heard.is_set() and commanded.is_set()) and time.monotonic() < deadline:
        chatter.publish(String(data=f"hello from robot1 #{i}"))
        twist = Twist()
        twist.linear.x, twist.angular.z = 0.5, 0.1 * i
        cmd.publish(twist)
        i += 1
        heard.wait(0.3)  # paces the talker; the loop ends as soon as both sides heard

    robot.close()
    base.close()
    for proc in bridges:
        proc.send_signal(signal.SIGINT)
    codes = [proc.wait(20) for proc in bridges]
    ok = heard.is_set() and commanded.is_set() and codes == [0, 0]
    print("\ndemo " + ("passed: messages crossed both ways" if ok else "FAILED"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
