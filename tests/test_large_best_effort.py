"""Best-effort 1 MB images through the file a user writes reach a best-effort subscriber whole.

Fast DDS sends a message larger than the writer's shared-memory segment (512 kB unless a
profile says otherwise) over its UDP transport, where a best-effort reader loses it whole when
one fragment is lost: about 6 images in 10 on the development machine. The far bridge is the
writer of the last hop, so ``rosgate run`` gives its participant an 8 MiB segment (rosgate's
``fastdds.xml``) unless the environment names a Fast DDS profile of its own.

The camera here is a separate process that runs with rosgate's profile as well (its own hop to
the near bridge is the camera driver's business, not rosgate's); the subscriber is this test's
process, with Fast DDS's defaults, as a user's node.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from conftest import settle, wait_until, warm_up
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgate_top.client import StatusClient
from std_msgs.msg import UInt8MultiArray
from test_big_images import camera_pair

import rosgate
from rosgate.cli import FASTDDS_PROFILES, large_shared_memory

COUNT = 40
SIZE = 1_000_000
PROFILE = Path(rosgate.__file__).with_name("fastdds.xml")

CAMERA = """
import sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt8MultiArray

count, size = int(sys.argv[1]), int(sys.argv[2])
rclpy.init()
node = rclpy.create_node("camera")
pub = node.create_publisher(UInt8MultiArray, "/camera",
                            QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
deadline = time.monotonic() + 60
while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
    time.sleep(0.05)
print("matched", flush=True)
sys.stdin.readline()  # the test says when the far side is ready
for i in range(count):
    # every image differs at both ends: one put together from two would show
    data = bytes([i]) * 1000 + bytes(size - 2000) + bytes([255 - i]) * 1000
    pub.publish(UInt8MultiArray(data=data))
    time.sleep(0.05)  # a camera's pace: 20 images a second
print("sent", flush=True)
sys.stdin.readline()  # the writer stays until the test has what it waits for (then: killed)
"""


def expected(i: int) -> bytes:
    return bytes([i]) * 1000 + bytes(SIZE - 2000) + bytes([255 - i]) * 1000


def crossing(tmp_path: Path, domain, ros_side, bridge,
             far_env: dict[str, str]) -> tuple[list[bytes], str]:
    """What a best-effort subscriber gets of COUNT best-effort images across a client and a
    server, the server (the far side, which publishes) started with ``far_env``; and, when
    some are missing, what the bridges counted (:func:`hops`)."""
    server_domain, client_domain = domain(), domain()
    server, client = camera_pair(tmp_path, "std_msgs/msg/UInt8MultiArray",
                                 "{reliability: best_effort, depth: 10}")
    bridge(server, server_domain, env=far_env)
    bridge(client, client_domain)
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    inbox = ros_side(server_domain, "far").listen("/camera", UInt8MultiArray, best_effort)
    # small messages from this process until one arrives: the session is up and both ends of
    # both DDS hops matched, so an image is not lost for that
    warm = ros_side(client_domain, "near").publisher("/camera", UInt8MultiArray, best_effort)
    warm_up(warm, inbox, UInt8MultiArray(data=b"w"))
    before = camera_count("robot1", "sent")
    camera = subprocess.Popen(
        [sys.executable, "-c", CAMERA, str(COUNT), str(SIZE)], text=True,
        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        env=dict(os.environ, ROS_DOMAIN_ID=str(client_domain),
                 FASTRTPS_DEFAULT_PROFILES_FILE=str(PROFILE)))
    try:
        assert camera.stdout is not None and camera.stdin is not None
        assert camera.stdout.readline().strip() == "matched"
        camera.stdin.write("go\n")
        camera.stdin.flush()
        assert camera.stdout.readline().strip() == "sent"
        images = lambda items: [m for m in items if len(m.data) == SIZE]
        # every image arrived, or the far bridge has dealt with each the near one sent (then
        # what it published and still may arrive is in once the listener has been quiet)
        wait_until(lambda: len(images(inbox.items)) >= COUNT or far_done(before), 10)
        settle(inbox, quiet=1.0)
        whole = len(images(inbox.items)) >= COUNT
        counted = "" if whole else hops()
    finally:
        camera.kill()
        camera.wait()
    return [bytes(m.data) for m in inbox.items if len(m.data) == SIZE], counted


def camera_count(name: str, counter: str) -> int:
    """Bridge ``name``'s count of /camera messages ``counter`` (sent, or received, lost or
    dropped: what it dealt with)."""
    with StatusClient(name) as ask:
        status = ask.status()
    entries = [e for e in status["entries"] if e["name"] == "/camera"]
    if counter != "dealt":
        return sum(e[counter] for e in entries)
    return sum(e["received"] + e["lost"] + sum(e["drops"].values()) for e in entries)


def far_done(before: int) -> bool:
    """The near bridge sent the camera's COUNT images (it sent ``before`` messages until then)
    and the far one has received, lost or dropped every message the near one sent."""
    sent = camera_count("robot1", "sent")
    return sent >= before + COUNT and camera_count("base", "dealt") >= sent


def hops() -> str:
    """What each bridge counted for /camera: the near one sent, the far one received and
    published, and what each dropped and why; and what their links dropped."""
    said = []
    for name in ("robot1", "base"):
        with StatusClient(name) as ask:
            status = ask.status()
        said += [f"{name}: sent {e['sent']}, received {e['received']}, drops {e['drops']}"
                 for e in status["entries"] if e["name"] == "/camera"]
        said += [f"{name} links: {status.get('link_drops')}"]
    return "; ".join(said)


def test_best_effort_1mb_images_reach_a_best_effort_subscriber_whole(tmp_path, domain, ros_side,
                                                                      bridge):
    env = {k: v for k, v in os.environ.items() if k not in FASTDDS_PROFILES}
    got, counted = crossing(tmp_path, domain, ros_side, bridge, env)
    assert len(got) >= COUNT - 1, f"{len(got)} of {COUNT} arrived; {counted}"
    indices = [image[0] for image in got]
    assert indices == sorted(set(indices)), indices  # in order, none twice
    for image in got:
        assert image == expected(image[0]), f"image {image[0]} differs"


def test_without_the_large_segment_the_same_images_are_lost(tmp_path, domain, ros_side, bridge):
    """The control: the far bridge told to use Fast DDS's defaults (a profile that sets nothing)
    loses most of them on its own hop, so the test above measures the segment."""
    defaults = tmp_path / "defaults.xml"
    defaults.write_text('<?xml version="1.0" encoding="UTF-8" ?>\n'
                        '<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"/>\n')
    env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(defaults))
    got, _ = crossing(tmp_path, domain, ros_side, bridge, env)
    assert len(got) <= COUNT * 0.9, f"{len(got)} of {COUNT} arrived"
    assert all(image == expected(image[0]) for image in got)  # what arrives is whole


def test_a_profile_of_the_users_own_is_left_alone(monkeypatch, tmp_path):
    environ = {k: v for k, v in os.environ.items()
               if k not in (*FASTDDS_PROFILES, "RMW_IMPLEMENTATION")}
    monkeypatch.setattr(os, "environ", environ)  # this process's own stays as it is
    monkeypatch.chdir(tmp_path)
    assert large_shared_memory() == PROFILE
    assert environ[FASTDDS_PROFILES[0]] == str(PROFILE) and PROFILE.is_file()

    for name in FASTDDS_PROFILES:  # either variable, set by the user, wins
        for other in FASTDDS_PROFILES:
            environ.pop(other, None)
        environ[name] = "/etc/mine.xml"
        assert large_shared_memory() is None
        assert environ[name] == "/etc/mine.xml" and len(
            [n for n in FASTDDS_PROFILES if n in environ]) == 1
    for other in FASTDDS_PROFILES:
        environ.pop(other, None)

    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").write_text("<profiles/>")  # Fast DDS reads it
    assert large_shared_memory() is None and FASTDDS_PROFILES[0] not in environ
    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").unlink()

    environ["RMW_IMPLEMENTATION"] = "rmw_cyclonedds_cpp"  # another middleware
    assert large_shared_memory() is None and FASTDDS_PROFILES[0] not in environ
    environ["RMW_IMPLEMENTATION"] = "rmw_fastrtps_dynamic_cpp"
    assert large_shared_memory() == PROFILE
