"""The ``rosgate`` command as a user meets it: one clear message per mistake, naming file, line
and key, exit status 2, never a traceback."""

from __future__ import annotations

import os
import re
import signal
import socket
import stat
import subprocess
import time
from pathlib import Path

import pytest
from conftest import ROSGATE, free_port
from cryptography.fernet import Fernet

from rosgate.wire import envelope


def rosgate(*args: str, env: dict[str, str] | None = None, cwd: Path | None = None,
            timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([ROSGATE, *args], capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, **(env or {})), cwd=cwd)


def user_error(result: subprocess.CompletedProcess) -> str:
    """Assert the shape of a user error and return its text."""
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("rosgate: error: "), result.stderr
    return result.stderr


GOOD = """\
bridge:
  name: robot1
  role: peer
  peer: 127.0.0.1
  listen: 127.0.0.1
topics:
  - topic: /chatter
    type: std_msgs/msg/String
    direction: transmit
    port: {port}
"""


@pytest.fixture
def config(tmp_path: Path):
    def write(text: str, name: str = "bringup.yaml") -> Path:
        path = tmp_path / name
        path.write_text(text)
        return path
    return write


def test_check_accepts_a_good_file(config):
    path = config(GOOD.format(port=12001))
    result = rosgate("check", str(path))
    assert result.returncode == 0, result.stderr
    assert "ok (peer 'robot1', 1 topic(s))" in result.stdout
    assert "/chatter -> /chatter  [std_msgs/msg/String] udp:12001 cdr none" in result.stdout


@pytest.mark.parametrize("change, line, key, words", [
    # YAML syntax
    (("    port: 12001\n", "    port: [12001\n"), 11, None, "YAML"),
    # unknown key, with a suggestion
    (("    port:", "    prot:"), 10, "topics[0].prot", "did you mean 'port'"),
    # missing required key
    (("    direction: transmit\n", ""), 7, "topics[0].direction", "missing"),
    # unknown plugin: names the installed ones and the distribution that would provide it
    (("    port:", "    codec: yaml\n    port:"), 10, "topics[0].codec",
     "pip install the distribution that provides it (by convention rosgate-codec-yaml)"),
    # message type that does not exist / package not installed
    (("std_msgs/msg/String", "std_msgs/msg/Strin"), 8, "topics[0].type",
     "has no msg 'Strin' (did you mean 'String'?)"),
    (("std_msgs/msg/String", "robot_msgs/msg/Arm"), 8, "topics[0].type",
     "'robot_msgs' is not installed (apt install ros-$ROS_DISTRO-robot-msgs, or pip install "
     "ros-jazzy-robot-msgs)"),
    # a package misspelt is not one to install: the installed one it resembles is named
    (("std_msgs/msg/String", "std_msg/msg/String"), 8, "topics[0].type",
     "interface package 'std_msg' is not installed (did you mean 'std_msgs'?)\n"),
    # a cipher whose key is missing
    (("    port:", "    cipher: fernet\n    port:"), 10, "topics[0].cipher",
     "fernet: fernet needs exactly one of key_file or key_env"),
])
def test_check_names_file_line_key_and_fix(config, change, line, key, words):
    path = config(GOOD.format(port=12001).replace(*change))
    text = user_error(rosgate("check", str(path)))
    assert f"{path}:{line}: " in text
    if key:
        assert f": {key}: " in text
    assert words in text


def test_missing_key_file_is_named(config):
    path = config("plugins:\n  fernet: {key_file: nowhere.key}\n" +
                  GOOD.format(port=12001).replace("    port:", "    cipher: fernet\n    port:"))
    text = user_error(rosgate("check", str(path)))
    assert f"{path}:2: plugins.fernet.key_file: cannot read key file" in text
    assert "rosgate keygen fernet" in text


def test_legacy_ros2_socket_bridge_file_is_recognised():
    legacy = Path(__file__).resolve().parent / "data" / "legacy" / "bringup.yaml"
    text = user_error(rosgate("check", str(legacy)))
    assert "ros2_socket_bridge" in text


def test_port_in_use_is_a_clear_error(config):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        path = config(GOOD.format(port=port).replace("direction: transmit", "direction: receive")
                      .replace("  listen:", "  insecure: true\n  listen:"))
        result = rosgate("run", str(path), env={"ROS_DOMAIN_ID": "3"})
    text = result.stderr  # after the warning that insecure: true says on every start
    assert result.returncode == 2 and "Traceback" not in text, text
    assert "INSECURE" in text and "\nrosgate: error: " in text
    assert f"{path}:11: topics[0].port: cannot bind UDP 127.0.0.1:{port}" in text


def test_a_server_whose_main_line_port_is_in_use_says_so_and_exits_cleanly(config, tmp_path):
    from rosgate import identity

    key = tmp_path / "base.key"
    identity.write_private(key, identity.generate())
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = config(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, "
                      f"identity: {key}}}\nclients: {{}}\n")
        result = rosgate("run", str(path), env={"ROS_DOMAIN_ID": "3"})
    text = user_error(result)
    assert f"bridge.server: cannot listen on TCP 127.0.0.1:{port}" in text, text
    assert "Fatal Python error" not in text and "Error:" not in text.split("error:", 1)[1]


def test_run_takes_the_domain_id_from_the_command_line(config, domain, ros_side):
    """--domain-id puts the bridge in that ROS domain, whatever ROS_DOMAIN_ID says."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as far:
        far.bind(("127.0.0.1", 0))
        far.settimeout(0.2)
        path = config(GOOD.format(port=far.getsockname()[1]))
        wanted = domain()
        proc = subprocess.Popen([ROSGATE, "run", str(path), "--domain-id", str(wanted)],
                                stderr=subprocess.DEVNULL, env=dict(os.environ, ROS_DOMAIN_ID="0"))
        try:
            from std_msgs.msg import String

            talker = ros_side(wanted, "talker").publisher("/chatter", String)
            deadline = time.monotonic() + 20
            while True:
                assert time.monotonic() < deadline, "nothing arrived from the bridge"
                talker.publish(String(data="in the asked-for domain"))
                try:
                    frame, _ = far.recvfrom(65536)
                except TimeoutError:
                    continue
                if not frame[3] & envelope.FLAG_ANNOUNCE:  # the topic's type, said first
                    break
            assert b"in the asked-for domain" in frame
        finally:
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(20) == 0


def test_run_stops_cleanly_on_sigterm(config, domain):
    path = config(GOOD.format(port=free_port()))
    proc = subprocess.Popen([ROSGATE, "run", str(path)], stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, ROS_DOMAIN_ID=str(domain())))
    assert proc.stderr is not None
    for line in proc.stderr:
        if "running as peer" in line:
            break
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0
    rest = proc.stderr.read()
    assert "stopping" in rest and "Traceback" not in rest


def test_run_stops_cleanly_on_a_burst_of_signals(config, domain):
    """SIGINT from a shell and its process group at once, and more while stopping: a handler
    that took a lock (Event.set) once hung a bridge for good inside its own Event.wait."""
    path = config(GOOD.format(port=free_port()))
    proc = subprocess.Popen([ROSGATE, "run", str(path)], stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, ROS_DOMAIN_ID=str(domain())))
    assert proc.stderr is not None
    for line in proc.stderr:
        if "running as peer" in line:
            break
    for _ in range(50):
        proc.send_signal(signal.SIGINT)
    assert proc.wait(20) == 0
    assert "Traceback" not in proc.stderr.read()


def test_plugins_lists_every_kind_with_its_distribution():
    result = rosgate("plugins")
    assert result.returncode == 0
    rows = {tuple(line.split()[:3]) for line in result.stdout.splitlines()[1:]}
    assert {("transport", "udp", "rosgate-transport-udp"),
            ("transport", "tcp", "rosgate-transport-tcp"), ("codec", "cdr", "rosgate"),
            ("codec", "msgpack", "rosgate-codec-msgpack"), ("cipher", "none", "rosgate"),
            ("cipher", "fernet", "rosgate-crypto-fernet")} <= rows


def test_a_broken_plugin_is_reported_by_name_and_the_rest_work(tmp_path, config):
    # a real entry point, as an installed distribution would declare it, whose module is missing
    dist = tmp_path / "site" / "rosgate_broken-1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: rosgate-broken\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[rosgate]\nbroken = rosgate_no_such_module\n")
    env = {"PYTHONPATH": str(tmp_path / "site")}
    result = rosgate("plugins", env=env)
    assert result.returncode == 0
    assert ("failed to load plugin 'broken' (rosgate-broken): ModuleNotFoundError: "
            "No module named 'rosgate_no_such_module'") in result.stdout
    assert "udp" in result.stdout
    assert rosgate("check", str(config(GOOD.format(port=12001))), env=env).returncode == 0


def test_a_plugin_whose_library_is_missing_is_reported_by_name_and_the_rest_work(config):
    """The libraries these plugins import only where they use them (they are slow to import) are
    still looked for when the plugin loads: without one, its plugin fails to load, by name."""
    missing = {"nacl": ("nacl", "rosgate-crypto-nacl"), "rich": ("top", "rosgate-top"),
               "prometheus_client": ("metrics", "rosgate-metrics-prometheus")}
    # None in sys.modules: what an import, and importlib's find_spec, take for "not installed"
    hide = f"import sys; sys.modules.update(dict.fromkeys({sorted(missing)!r})); "

    def rosgate_without(*args: str) -> subprocess.CompletedProcess:
        code = hide + f"from rosgate.cli import main; sys.exit(main({list(args)!r}))"
        return subprocess.run([str(Path(ROSGATE).with_name("python")), "-c", code],
                              capture_output=True, text=True, timeout=60,
                              env=dict(os.environ, NACL_KEY="A" * 43 + "="))

    listing = rosgate_without("plugins")
    assert listing.returncode == 0, listing.stderr
    for library, (plugin, distribution) in missing.items():
        assert (f"failed to load plugin {plugin!r} ({distribution}): ModuleNotFoundError: "
                f"No module named {library!r}") in listing.stdout
    rows = {tuple(line.split()[:2]) for line in listing.stdout.splitlines()}
    assert ("transport", "udp") in rows and ("cipher", "aead") in rows
    assert not {("cipher", "nacl"), ("monitor", "metrics"), ("command", "top")} & rows

    path = config(GOOD.format(port=12001).replace("    port:", "    cipher: nacl\n    port:")
                  + "plugins:\n  nacl: {key_env: NACL_KEY}\n")
    check = rosgate_without("check", str(path))
    assert check.returncode == 2 and "Traceback" not in check.stderr, check.stderr
    # check loads every plugin: each that failed is named first, then the file's error
    *warnings, text = check.stderr.split("rosgate: ")
    for library, (plugin, distribution) in missing.items():
        assert (f"warning: plugin {plugin!r} ({distribution}) failed to load: "
                f"ModuleNotFoundError: No module named {library!r}") in "".join(warnings)
    assert text.startswith(f"error: {path}:10: topics[0].cipher: unknown cipher 'nacl' "
                           "(installed ciphers: "), text
    assert ("plugin 'nacl' is installed but failed to load: ModuleNotFoundError: No module "
            "named 'nacl'") in text
    assert "fix: repair or reinstall rosgate-crypto-nacl, or pick an installed cipher" in text
    # the same file, nacl there: it passes
    result = rosgate("check", str(path), env={"NACL_KEY": "A" * 43 + "="})
    assert result.returncode == 0, result.stderr


def test_a_plugin_whose_library_is_installed_but_broken_is_named_where_it_is_used(tmp_path,
                                                                                   config):
    """Installed, such a library passes the plugin's load; it fails where the plugin imports it
    (a cipher made, a command run), and the error names the plugin, without a traceback."""
    site = tmp_path / "site"
    for library in ("nacl", "rich"):
        (site / library).mkdir(parents=True)
        (site / library / "__init__.py").write_text(
            f"raise ImportError('lib{library}.so: cannot open shared object file')\n")
    env = {"PYTHONPATH": str(site), "NACL_KEY": "A" * 43 + "="}
    path = config(GOOD.format(port=12001).replace("    port:", "    cipher: nacl\n    port:")
                  + "plugins:\n  nacl: {key_env: NACL_KEY}\n")
    for args, plugin, distribution, library in [
            (("check", str(path)), "nacl", "rosgate-crypto-nacl", "nacl"),
            (("top", "robot1", "--once"), "top", "rosgate-top", "rich")]:
        text = user_error(rosgate(*args, env=env))
        assert text.startswith(
            f"rosgate: error: plugin {plugin!r} ({distribution}) failed to load: ImportError: "
            f"lib{library}.so: cannot open shared object file ({site / library / '__init__.py'}:1)"
            f"\n  fix: repair or reinstall {distribution}\n"), text


def test_blocked_plugin_is_named_when_asked_for(config):
    env = {"ROSGATE_DISABLE_PLUGINS": "msgpack"}
    assert "blocked plugin 'msgpack'" in rosgate("plugins", env=env).stdout
    path = config(GOOD.format(port=12001).replace("    port:", "    codec: msgpack\n    port:"))
    text = user_error(rosgate("check", str(path), env=env))
    assert "blocked by ROSGATE_DISABLE_PLUGINS" in text


def test_keygen_writes_a_private_key_and_never_overwrites(tmp_path):
    key = tmp_path / "secret.key"
    result = rosgate("keygen", "fernet", "--out", str(key))
    assert result.returncode == 0, result.stderr
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    Fernet(key.read_bytes().strip())  # a usable key
    first = key.read_bytes()
    assert "exists" in user_error(rosgate("keygen", "fernet", "--out", str(key)))
    assert key.read_bytes() == first
    assert rosgate("keygen", "fernet", "--out", str(key), "--force").returncode == 0
    assert key.read_bytes() != first
    assert "takes no key" in user_error(rosgate("keygen", "none", "--out", str(tmp_path / "n")))


BT_CLIENT = """\
bridge:
  name: robot1
  role: client
  server: {server}
  main_line: bt
{plugins}topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit, transport: bt, port: {port}}}
"""


@pytest.mark.skipif(hasattr(socket, "AF_BLUETOOTH"), reason="this Python has Bluetooth support")
def test_check_on_a_python_without_bluetooth_names_the_key(config):
    result = rosgate("check", str(config(BT_CLIENT.format(server="AA:BB:CC:DD:EE:FF/5", plugins="",
                                                          port=6))))
    message = user_error(result)
    assert "bringup.yaml:5: bridge.main_line: bt: this Python was built without Bluetooth " \
           "support (socket.AF_BLUETOOTH)" in message
    assert "libbluetooth-dev" in message


@pytest.mark.parametrize("server, port, line, says", [
    ("127.0.0.1:12000", 6, "4: bridge.server", "'127.0.0.1:12000' is not a device address and an "
                                               "RFCOMM channel, for example AA:BB:CC:DD:EE:FF/5"),
    ("AA:BB:CC:DD:EE:FF/31", 6, "4: bridge.server", "RFCOMM channel 31 is out of range"),
    ("AA:BB:CC:DD:EE:FF/5", 12001, "9: topics[0].port", "RFCOMM channel 12001 is out of range"),
])
def test_check_bt_addresses(config, server, port, line, says):
    plugins = "plugins:\n  bt: {emulate_dir: /tmp}\n"
    message = user_error(rosgate("check", str(config(BT_CLIENT.format(server=server,
                                                                     plugins=plugins, port=port)))))
    assert f"bringup.yaml:{line}: {says}" in message


def test_check_refuses_an_ip_topic_addressed_by_a_bluetooth_main_line(config):
    """udp and tcp topics go to the server's host: a device address is no IP host."""
    text = BT_CLIENT.format(server="AA:BB:CC:DD:EE:FF/5",
                            plugins="plugins:\n  bt: {emulate_dir: /tmp}\n",
                            port=6).replace("transport: bt", "transport: udp")
    message = user_error(rosgate("check", str(config(text))))
    assert "bringup.yaml:9: topics[0].port: 'AA:BB:CC:DD:EE:FF' is not an IP address or host " \
           "name" in message
    assert "fix: this topic's udp address is bridge.server with port 6" in message


SERVICE = """\
services:
  - service: /mcu/ping
    type: std_srvs/srv/Trigger
    direction: transmit
    remote: ping
    transport: tcp
    port: 20001
    codec: msgpack
    framing: serial_datagram
"""


def test_check_lists_services(config):
    path = config(GOOD.format(port=12001) + SERVICE)
    result = rosgate("check", str(path))
    assert result.returncode == 0, result.stderr
    assert "ok (peer 'robot1', 1 topic(s), 1 service(s))" in result.stdout
    assert "/mcu/ping -> ping  [std_srvs/srv/Trigger] tcp:20001 msgpack none" in result.stdout


@pytest.mark.parametrize("change, line, key, words", [
    (("    transport: tcp\n", "    transport: udp\n"), 16, "services[0].transport",
     "framing serial_datagram needs a stream transport"),
    (("    codec: msgpack\n", "    codec: cdr\n"), 18, "services[0].codec",
     "codec cdr does not put the service's name on the wire"),
    (("std_srvs/srv/Trigger", "std_srvs/srv/Trigga"), 13, "services[0].type",
     "has no srv 'Trigga'"),
])
def test_check_names_service_errors(config, change, line, key, words):
    path = config((GOOD.format(port=12001) + SERVICE).replace(*change))
    text = user_error(rosgate("check", str(path)))
    assert f"{path}:{line}: {key}: " in text
    assert words in text


def test_check_on_a_server_prints_what_each_client_may_do(tmp_path):
    """The policy a server will enforce, a line per rule, in the client's words turned into
    what it may do here; a client without rules is said to bridge nothing."""
    keys = [subprocess.run([ROSGATE, "keygen", "identity", "--out", str(tmp_path / f"{n}.key")],
                           capture_output=True, text=True, timeout=60, check=True).stdout.strip()
            for n in ("base", "robot1", "robot2", "robot3")]
    server = tmp_path / "base.yaml"
    server.write_text(
        f"bridge: {{name: base, role: server, server: 127.0.0.1:{free_port()}, "
        f"identity: {tmp_path / 'base.key'}}}\n"
        "clients:\n"
        f"  robot1: {{key: {keys[1]}, topics: [{{name: /robot1/**, direction: transmit}}, "
        "{name: /cmd_vel, direction: receive, types: [geometry_msgs/msg/Twist], ports: [12001, "
        "12010-12019], ciphers: [aead]}], services: [{name: /reset, direction: transmit}], "
        "actions: [{name: /fib, direction: receive}]}\n"
        f"  robot2: {{key: {keys[2]}, topics: [{{name: /robot2/scan, direction: both}}]}}\n"
        f"  robot3: {{key: {keys[3]}}}\n")
    result = subprocess.run([ROSGATE, "check", str(server)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [
        f"{server}: ok (server 'base', 0 topic(s), 3 client(s))",
        "  robot1 may send topic /robot1/**  [any type]  ciphers any, main port only",
        "  robot1 may take topic /cmd_vel  [geometry_msgs/msg/Twist]  ciphers aead, "
        "ports 12001, 12010-12019",
        "  robot1 may call service /reset  [any type]  ciphers any, main port only",
        "  robot1 may serve goals of action /fib  [any type]  ciphers any, main port only",
        "  robot2 may send and take topic /robot2/scan  [any type]  ciphers any, main port only",
        "  robot3 may bridge nothing (no rules: every entry refused)"]


def test_a_running_bridge_s_log_lines_carry_the_time_and_its_name(tmp_path, domain, bridge):
    """ISO 8601 to the millisecond with the zone's offset, then who speaks: an operator greps
    one bridge's lines and times a reconnect from the log alone."""
    peer = tmp_path / "peer.yaml"
    peer.write_text("bridge: {name: far, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, "
                    "insecure: true}\ntopics:\n  - {topic: /x, type: std_msgs/msg/String, "
                    f"direction: transmit, port: {free_port()}}}\n")
    running = bridge(peer, domain())
    line = next(x for x in running.lines if "running as" in x)
    stamp, _, rest = line.partition(" ")
    when = time.strptime(stamp[:19], "%Y-%m-%dT%H:%M:%S")
    assert abs(time.mktime(when) - time.time()) < 300, line
    assert re.fullmatch(r"\.\d{3}[+-]\d{4}", stamp[19:]), line
    assert rest.startswith("[rosgate far] INFO "), line


def _installed(tmp_path: Path, name: str, source: str) -> dict[str, str]:
    """A plugin installed as a distribution would be (a dist-info with its entry point, its
    module beside it); the environment that finds it."""
    site = tmp_path / "site"
    dist = site / f"rosgate_{name}-1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: rosgate-{name}\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(f"[rosgate]\n{name} = rosgate_{name}\n")
    (site / f"rosgate_{name}.py").write_text(source)
    return {"PYTHONPATH": str(site)}


def test_a_plugin_of_the_first_api_that_imports_the_old_kit_is_told_where_it_went(tmp_path):
    """Written from the first release's docs: its tests' kit was rosgate.testing. It is refused
    by name, with the API version and the one-line fix, and the rest work."""
    env = _installed(tmp_path, "oldcodec", "from rosgate.testing import codec_suite\n")
    listing = rosgate("plugins", env=env)
    assert listing.returncode == 0
    assert ("failed to load plugin 'oldcodec' (rosgate-oldcodec): ModuleNotFoundError: No module "
            "named 'rosgate.testing'") in listing.stdout
    assert ("since rosgate plugin API 2: the plugin kit is a distribution of its own: pip "
            "install rosgate-testing, and import rosgate_testing (docs/plugin-api.md)") \
        in listing.stdout
    assert ("codec", "cdr", "rosgate") in {tuple(line.split()[:3])
                                           for line in listing.stdout.splitlines()}


def test_a_plugin_written_for_a_newer_api_is_refused_by_name_with_the_version(tmp_path):
    env = _installed(tmp_path, "future", "ROSGATE_API = 3\n"
                     "from rosgate import hookimpl\n"
                     "@hookimpl\ndef rosgate_codecs(register):\n    raise AssertionError\n")
    listing = rosgate("plugins", env=env)
    assert listing.returncode == 0
    assert ("failed to load plugin 'future' (rosgate-future): written for rosgate plugin API 3; "
            "this rosgate serves API 2: upgrade rosgate") in listing.stdout


def test_a_plugin_that_says_the_api_of_this_rosgate_loads(tmp_path):
    env = _installed(tmp_path, "current", "ROSGATE_API = 2\n"
                     "from rosgate import Command, hookimpl\n"
                     "def hello(args):\n    print('hello')\n    return 0\n"
                     "@hookimpl\ndef rosgate_commands(register):\n"
                     "    register(Command('hello', 'says hello', hello))\n")
    listing = rosgate("plugins", env=env)
    assert "failed to load plugin 'current'" not in listing.stdout, listing.stdout
    assert rosgate("hello", env=env).stdout == "hello\n"
