"""`make demo`: two rosgate bridges on loopback, a talker on one side and a listener on the other.

The robot side (ROS domain 201) and the base-station side (domain 202) cannot see each other
over DDS; everything the listener prints came through the bridge: /chatter as msgpack over UDP,
/cmd_vel as CDR over the TCP main line the other way. The session is authenticated: the demo
makes an identity for each side in a temporary folder (``rosgate keygen identity``), the server
lists the robot's public key with a policy, and every frame is sealed with the session's keys
(the default cipher, aead). Exits by itself.
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
  identity: base.key                # this side's private key (0600)
clients:                            # who may connect (by public key), and what each may do
  robot1:
    key: {{robot1_key}}
    topics:
      - {{{{name: /robot1/**, direction: both}}}}
"""

CLIENT = f"""\
bridge:
  name: robot1
  role: client
  server: 127.0.0.1:{PORT}
  identity: robot1.key
  server_key: {{base_key}}           # the server's public key
topics:
  - topic: /chatter                 # robot -> base, MessagePack over UDP
    type: std_msgs/msg/String
    direction: transmit
    remote: /robot1/chatter
    transport: udp
    codec: msgpack
  - topic: /cmd_vel                 # base -> robot, on the TCP main line
    type: geometry_msgs/msg/Twist
    direction: receive
    remote: /robot1/cmd_vel
    transport: tcp
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
    public = {}
    for name in ("base", "robot1"):  # prints each public key; the private key stays in the file
        public[name] = subprocess.run(
            [ROSGATE, "keygen", "identity", "--out", str(work / f"{name}.key")], check=True,
            capture_output=True, text=True).stdout.strip()
    server, client = SERVER.format(robot1_key=public["robot1"]), CLIENT.format(
        base_key=public["base"])
    (work / "server.yaml").write_text(server)
    (work / "client.yaml").write_text(client)
    print(f"configs and keys in {work}\n--- server.yaml ---\n{server}--- client.yaml ---\n"
          f"{client}")
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
