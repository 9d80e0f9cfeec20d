"""End to end: two ``rosgate run`` processes, each talking to a ROS side in its own DDS domain,
so the only way a message gets across is through the bridge. What arrives is compared with
what was sent, field for field and byte for byte."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from conftest import ROSGATE, cross, free_port
from geometry_msgs.msg import Twist
from sensor_msgs.msg import Image
from std_msgs.msg import String


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.fixture
def fernet_key(tmp_path: Path) -> Path:
    key = tmp_path / "secret.key"
    subprocess.run([ROSGATE, "keygen", "fernet", "--out", str(key)], check=True,
                   capture_output=True)
    return key


# -- messages: make(None) is a warm-up message, make(i) the i-th numbered one --------------
def string(i: int | None) -> String:
    return String(data="warmup" if i is None else f"msg-{i:04d}-" + "é" * 50 + "x" * 100)


def twist(i: int | None) -> Twist:
    t = Twist()
    t.linear.x = -1.0 if i is None else float(i)
    t.linear.y = 0.25
    t.angular.z = 0.0 if i is None else i * 0.5
    return t


def image(i: int | None) -> Image:
    img = Image()
    img.header.frame_id = "warmup" if i is None else f"camera-{i}"
    img.height, img.width, img.encoding, img.step = 1024, 1024, "mono8", 1024
    seed = 0 if i is None else i + 1
    img.data = (bytes((b * 7 + seed) & 0xFF for b in range(251)) * 4177
                + bytes(1024 * 1024 - 251 * 4177))
    return img


def assert_strings(got: list[String], count: int, ordered: bool) -> None:
    expected = [string(i).data for i in range(count)]
    data = [m.data for m in got]
    assert (data if ordered else sorted(data)) == expected


# -- peer role: both files complete, no main line ----------------------------------------
def test_peer_udp_strings_cross_both_ways(tmp_path, domain, ros_side, bridge):
    da, db = domain(), domain()
    p1, p2 = free_port(), free_port()
    a = write(tmp_path / "a.yaml", f"""
bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit, port: {p1}}}
  - {{topic: /reply, type: std_msgs/String, direction: receive, port: {p2}, remote: /answer}}
""")
    b = write(tmp_path / "b.yaml", f"""
bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: receive, port: {p1}}}
  - {{topic: /answer, type: std_msgs/msg/String, direction: transmit, port: {p2}, remote: /reply}}
""")
    bridge(a, da), bridge(b, db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")

    forward = cross(side_a.publisher("/chatter", String), side_b.listen("/chatter", String),
                    string, lambda m: m.data == "warmup", 30)
    assert_strings(forward, 30, ordered=False)
    back = cross(side_b.publisher("/answer", String), side_a.listen("/reply", String),
                 string, lambda m: m.data == "warmup", 30)
    assert_strings(back, 30, ordered=False)


def test_peer_stream_image_1mb_msgpack(tmp_path, domain, ros_side, bridge, stream_kind):
    da, db = domain(), domain()
    k = stream_kind
    port = k.port()
    a = write(tmp_path / "a.yaml", f"""
bridge: {{name: a, role: peer, peer: '{k.host}', listen: '{k.host}'}}
plugins: {k.plugins}
topics:
  - {{topic: /camera, type: sensor_msgs/msg/Image, direction: transmit, port: {port},
      transport: {k.name}, codec: msgpack}}
""")
    b = write(tmp_path / "b.yaml", f"""
bridge: {{name: b, role: peer, peer: '{k.host}', listen: '{k.host}'}}
plugins: {k.plugins}
topics:
  - {{topic: /camera, type: sensor_msgs/msg/Image, direction: receive, port: {port},
      transport: {k.name}, codec: msgpack}}
""")
    bridge(b, db), bridge(a, da)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    got = cross(side_a.publisher("/camera", Image, 5), side_b.listen("/camera", Image, 5),
                image, lambda m: m.header.frame_id == "warmup", 3, interval=0.2)
    assert [m.header.frame_id for m in got] == ["camera-0", "camera-1", "camera-2"]
    for i, m in enumerate(got):
        assert bytes(m.data) == bytes(image(i).data)
        assert (m.height, m.width, m.encoding, m.step) == (1024, 1024, "mono8", 1024)


# -- client/server: the client's file holds the topics ------------------------------------
def server_file(tmp_path: Path, port: int, key: Path | None = None) -> Path:
    plugins = f"plugins: {{fernet: {{key_file: {key}}}}}\n" if key else ""
    return write(tmp_path / "server.yaml", f"""
bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}
{plugins}""")


def test_client_server_stream_twist_msgpack_fernet_both_ways(tmp_path, domain, ros_side, bridge,
                                                              fernet_key, stream_kind):
    dc, ds = domain(), domain()
    k = stream_kind
    port = k.port()
    client = write(tmp_path / "client.yaml", f"""
bridge:
  name: robot1
  role: client
  server: '{k.address(port)}'
  main_line: {k.name}
  defaults: {{transport: {k.name}, codec: msgpack, cipher: fernet}}
plugins:
  fernet: {{key_file: {fernet_key}}}
  {k.name}: {k.options}
topics:
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: receive, remote: /robot1/cmd_vel}}
  - {{topic: /odom_twist, type: geometry_msgs/msg/Twist, direction: transmit,
      remote: /robot1/odom_twist}}
""")
    bridge(write(tmp_path / "server.yaml", f"""
bridge: {{name: base, role: server, server: '{k.address(port)}', main_line: {k.name}}}
plugins:
  fernet: {{key_file: {fernet_key}}}
  {k.name}: {k.options}
"""), ds)
    bridge(client, dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    warm = lambda m: m.linear.x == -1.0

    down = cross(base.publisher("/robot1/cmd_vel", Twist), robot.listen("/cmd_vel", Twist),
                 twist, warm, 40)
    assert down == [twist(i) for i in range(40)]  # a stream: complete and in order
    up = cross(robot.publisher("/odom_twist", Twist), base.listen("/robot1/odom_twist", Twist),
               twist, warm, 40)
    assert up == [twist(i) for i in range(40)]


def test_client_server_udp_image_1mb_fernet(tmp_path, domain, ros_side, bridge, fernet_key):
    dc, ds = domain(), domain()
    port = free_port()
    client = write(tmp_path / "client.yaml", f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
plugins: {{fernet: {{key_file: {fernet_key}}}}}
topics:
  - {{topic: /camera, type: sensor_msgs/msg/Image, direction: transmit, cipher: fernet, qos: 5}}
""")
    bridge(server_file(tmp_path, port, fernet_key), ds)
    bridge(client, dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    got = cross(robot.publisher("/camera", Image, 5), base.listen("/camera", Image, 5),
                image, lambda m: m.header.frame_id == "warmup", 3, interval=0.3)
    assert sorted(m.header.frame_id for m in got) == ["camera-0", "camera-1", "camera-2"]
    for m in got:
        i = int(m.header.frame_id.split("-")[1])
        assert bytes(m.data) == bytes(image(i).data)


def test_client_server_udp_strings_server_to_client_own_port(tmp_path, domain, ros_side, bridge):
    """A server->client datagram topic: the server learns where the client is from its hello."""
    dc, ds = domain(), domain()
    port, own = free_port(), free_port()
    client = write(tmp_path / "client.yaml", f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /status, type: std_msgs/msg/String, direction: receive, port: {own},
      codec: msgpack}}
  - {{topic: /log, type: std_msgs/msg/String, direction: transmit}}
""")
    bridge(server_file(tmp_path, port), ds)
    bridge(client, dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    got = cross(base.publisher("/status", String), robot.listen("/status", String),
                string, lambda m: m.data == "warmup", 30)
    assert_strings(got, 30, ordered=False)
    got = cross(robot.publisher("/log", String), base.listen("/log", String),
                string, lambda m: m.data == "warmup", 30)
    assert_strings(got, 30, ordered=False)


def test_two_clients_on_one_server(tmp_path, domain, ros_side, bridge):
    """One server accepts many clients, each with its own topics."""
    d1, d2, ds = domain(), domain(), domain()
    port = free_port()
    bridge(server_file(tmp_path, port), ds)
    for name, d in (("robot1", d1), ("robot2", d2)):
        bridge(write(tmp_path / f"{name}.yaml", f"""
bridge: {{name: {name}, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit, remote: /{name}/chatter}}
"""), d)
    base = ros_side(ds, "base")
    for name, d in (("robot1", d1), ("robot2", d2)):
        got = cross(ros_side(d, name).publisher("/chatter", String),
                    base.listen(f"/{name}/chatter", String), string,
                    lambda m: m.data == "warmup", 10)
        assert_strings(got, 10, ordered=False)


def test_client_server_processes_serve_calls_both_ways_encrypted(tmp_path, domain, ros_side,
                                                                 bridge, fernet_key):
    from std_srvs.srv import SetBool, Trigger
    from test_services import DEEP, Caller, echo_set_bool, pong

    dc, ds = domain(), domain()
    port = free_port()
    client = write(tmp_path / "client.yaml", f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
plugins: {{fernet: {{key_file: {fernet_key}}}}}
services:
  - {{service: /set, type: std_srvs/srv/SetBool, direction: transmit, remote: /robot1/set,
     cipher: fernet, timeout: 2}}
  - {{service: /trig, type: std_srvs/srv/Trigger, direction: receive, transport: tcp,
     codec: msgpack, cipher: fernet, timeout: 2}}
""")
    server = bridge(server_file(tmp_path, port, fernet_key), ds)
    bridge(client, dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    base.ros.node.create_service(SetBool, "/robot1/set", echo_set_bool, qos_profile=DEEP)
    robot.ros.node.create_service(Trigger, "/trig", pong, qos_profile=DEEP)
    set_bool, trigger = Caller(robot, SetBool, "/set"), Caller(base, Trigger, "/trig")
    assert set_bool.warm_up(SetBool.Request(data=True))[0].message == "data=True"
    assert trigger.warm_up(Trigger.Request())[0] == Trigger.Response(success=True, message="pong")
    answers = set_bool.call_many([SetBool.Request(data=i % 2 == 0) for i in range(20)], 10)
    assert [a.message for a in answers] == [f"data={i % 2 == 0}" for i in range(20)]
    assert server.wait_log("client 'robot1' up: connected", 5)
