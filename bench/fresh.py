"""Fresh data under overload: the best-effort 2.5 kB topic through the default file, at twice
its sustained rate, and where its messages wait on the way.

    .venv/bin/python bench/fresh.py [--sustained MSG/S] [--seconds S] [--base REV] [--check]
                                    [--twist] [--twist-port] [--probe] [--repeat N]

It finds the sustained rate of the default file with every queue best effort (a short search,
as ``bench.py --quick``), then offers twice that in fresh processes and reports, of what the
subscriber got: the share delivered, p50/p99 age, the age of the messages sent in the trial's
second half, and the drops both bridges counted by reason (with ``--check``, the same at 0.9x
the sustained rate: a bridge that keeps up should drop nothing). With ``--base REV`` the same
trials run with the rosgate of git revision REV too, back to back (the same rates, REV first).
With ``--probe`` each bridge also records the age of every message at each hop (bridge A:
when its subscription gave it to the bridge; bridge B: when its datagram reached the machine,
and when it was published) and the script prints their percentiles: where the time goes.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import replace
from pathlib import Path

from processes import ROOT, Checkout, bringup_files, free_port, next_domains, ros_env

import bench
from bench import (
    DEFAULT_BE,
    DROP_CHECK,
    OVERLOAD,
    QUICK,
    SIZES,
    Case,
    counted_drops,
    find_sustained,
    log,
)

SIZE = next(s for s in SIZES if s.name == "2.5 kB")

# a sitecustomize for the bridges (--probe): ages per hop, written when the bridge exits
PROBE = textwrap.dedent('''
    import atexit, json, os, struct, sys, time
    if "rosgate" in os.path.basename(sys.argv[0] if sys.argv else ""):
        from rosgate import routes
        from collections import defaultdict
        ages = defaultdict(lambda: defaultdict(list))  # trial -> hop -> ages (ns)
        twist = defaultdict(lambda: defaultdict(list))  # the Twist's, by the bulk's trial
        TWIST_CDR = 4 + 6 * 8  # a Twist's CDR: the encapsulation header, six doubles
        last = [0]

        def stamp(data):
            "The publisher's send time, and the trial's ages (by the trial it names)."
            if len(data) == TWIST_CDR:  # --twist: its send time (s) in linear.x
                return int(struct.unpack_from("<d", data, 4)[0] * 1e9), twist[last[0]]
            try:
                sent, trial = int(bytes(data[8:24]), 16), int(bytes(data[24:32]), 16)
            except ValueError:
                return 0, None
            last[0] = max(last[0], trial)
            return sent, ages[trial]

        encode = routes.TransmitRoute._encode
        def _encode(self, message):
            sent, hops = stamp(message)
            if sent:
                hops["A taken"].append(time.time_ns() - sent)
            return encode(self, message)
        routes.TransmitRoute._encode = _encode

        accept = routes.ReceiveRoute.accept
        def accept_(self, header, payload, size, arrived=0):
            sent, hops = stamp(payload)
            if sent and arrived:
                hops["B arrived"].append(arrived - sent)
                hops["B waited here"].append(time.time_ns() - arrived)
            return accept(self, header, payload, size, arrived)
        routes.ReceiveRoute.accept = accept_

        deliver = routes.ReceiveRoute.deliver
        def deliver_(self, payload, size):
            sent, hops = stamp(payload)
            deliver(self, payload, size)
            if sent:
                hops["B published"].append(time.time_ns() - sent)
        routes.ReceiveRoute.deliver = deliver_

        def write():
            out = os.environ["ROSGATE_PROBE_OUT"] + f".{os.getpid()}.json"
            with open(out, "w") as f:
                found = dict(ages.get(last[0], {}))  # the last trial's: the overload
                found.update({f"twist: {hop}": v for hop, v in twist.get(last[0], {}).items()})
                json.dump(found, f)
        atexit.register(write)
''')


# a 20 Hz Twist beside the bulk topic, priority real_time (--twist): its own two processes
TWIST_PUB = textwrap.dedent('''
    import sys, threading, time, rclpy
    from geometry_msgs.msg import Twist
    rclpy.init()
    node = rclpy.create_node("fresh_twist_pub")
    publisher = node.create_publisher(Twist, "/cmd_vel", 10)
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
    print("ready", flush=True)
    while not stop.wait(0.05):  # 20 Hz, each message stamped with its send time
        message = Twist()
        message.linear.x = time.time()
        publisher.publish(message)
''')
TWIST_SUB = textwrap.dedent('''
    import json, sys, threading, time, rclpy
    from geometry_msgs.msg import Twist
    rclpy.init()
    node = rclpy.create_node("fresh_twist_sub")
    got = []
    node.create_subscription(Twist, "/cmd_vel", lambda m: got.append(
        (m.linear.x, time.time() - m.linear.x)), 10)
    threading.Thread(target=rclpy.spin, args=(node,), daemon=True).start()
    print("ready", flush=True)
    sys.stdin.readline()
    print(json.dumps(got), flush=True)
''')


def with_twist(write, own_port: bool = False):
    """bringup_files, with a Twist (/cmd_vel, priority real_time) beside the topic: in the
    client's list and in what the server lets it bridge (``own_port``: on a port of its own)."""
    def files(*args, **kwargs):
        a, b = write(*args, **kwargs)
        port = free_port() if own_port else None
        twist = ("  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, "
                 f"qos: 10, priority: real_time{f', port: {port}' if port else ''}}}\n")
        a.write_text(a.read_text() + twist)
        b.write_text(b.read_text().replace(
            "topics: [{name: /bench, direction: transmit}]",
            "topics: [{name: /bench, direction: transmit}, "
            f"{{name: /cmd_vel, direction: transmit{f', ports: [{port}]' if port else ''}}}]"))
        return a, b
    return files


def percentiles(values: list[int]) -> str:
    values = sorted(values)

    def pick(q: float) -> float:
        return values[min(len(values) - 1, int(q * len(values)))] / 1e6

    return (f"n={len(values):6d}  p50 {pick(0.5):7.1f} ms  p90 {pick(0.9):7.1f}  "
            f"p99 {pick(0.99):7.1f}")


def base_checkout(rev: str, folder: Path) -> Checkout:
    """REV's sources in ``folder``, run with this checkout's .venv (the sources go first on the
    bridges' path; the entry points are the same distributions')."""
    root = folder / "base"
    root.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(root)], input=archive, check=True)
    (root / ".venv").symlink_to(ROOT / ".venv")
    short = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", rev], check=True,
                           capture_output=True, text=True).stdout.strip()
    return Checkout(short, root)


#: --twist: a Twist beside the topic; the DDS domains of each case (publisher's, subscriber's)
TWIST = False
DOMAINS: list[tuple[int, int]] = []


def _domains() -> tuple[int, int]:
    DOMAINS.append(next_domains())
    return DOMAINS[-1]


def sustained_rate(checkout: Checkout, folder: Path) -> float:
    """The sustained rate of the case (a short search, as bench.py --quick)."""
    with Case(SIZE, replace(DEFAULT_BE, rev=checkout.rev), folder, checkout,
              reliability="best_effort") as case:
        case.warm_up()
        sustained, _ = find_sustained(case, QUICK)
    if sustained is None:
        raise SystemExit("no sustained rate found")
    return sustained.offered


def trial(checkout: Checkout, folder: Path, rate: float, seconds: float,
          probe: Path | None) -> dict:
    """One trial at ``rate`` in fresh processes: what the subscriber got, what the bridges
    dropped, and (``probe``) the ages per hop."""
    case = Case(SIZE, replace(DEFAULT_BE, rev=checkout.rev), folder, checkout,
                reliability="best_effort")
    twist: list[float] = []
    with case:
        case.warm_up()
        if not TWIST:
            t = case.trial(rate, seconds)
        else:
            pub_domain, sub_domain = DOMAINS[-1]
            ends = [subprocess.Popen([sys.executable, "-c", code], env=ros_env(domain),
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
                    for code, domain in ((TWIST_SUB, sub_domain), (TWIST_PUB, pub_domain))]
            try:
                for end in ends:
                    assert end.stdout is not None and end.stdout.readline().strip() == "ready"
                time.sleep(3.0)  # discovery, and the bridge's route for the new publisher
                start = time.time()
                t = case.trial(rate, seconds)
            finally:
                out = [end.communicate("quit\n", timeout=30)[0] for end in ends]
            twist = [wait for sent, wait in json.loads(out[0])
                     if start <= sent <= start + seconds]
    found = {"offered": round(t.offered), "delivered in time": f"{t.in_time / t.sent:.1%}",
             "arrived at all": f"{t.arrived:.1%}",
             "p50 ms": t.p50_us and round(t.p50_us / 1e3, 1),
             "p99 ms": t.p99_us and round(t.p99_us / 1e3, 1),
             "p99 settled ms": t.p99_settled_us and round(t.p99_settled_us / 1e3, 1),
             "drops": counted_drops(case),
             # a link's own (receive_buffer_full...), the last of each bridge's lines
             "link drops": [line.rsplit("frames for no topic: ", 1)[1] for bridge in case.bridges
                            for line in [*[seen for seen in bridge.lines.seen
                                           if "frames for no topic: " in seen][-1:]]]}
    if TWIST:
        found["twist (20 Hz, real_time) during the trial"] = (
            percentiles([int(w * 1e9) for w in twist]) if twist else "none arrived")
    if probe is not None:
        for path in sorted(probe.parent.glob(probe.name + ".*.json")):
            for hop, values in json.loads(path.read_text()).items():
                found[f"hop {hop}"] = percentiles(values)
            path.unlink()
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sustained", type=float, help="take this (msg/s) as the sustained "
                        "rate instead of searching for it")
    parser.add_argument("--check", action="store_true",
                        help=f"also a trial at {DROP_CHECK:g}x sustained (drops there?)")
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--base", help="also run REV's rosgate, first, at the same rate")
    parser.add_argument("--probe", action="store_true", help="ages per hop in the bridges")
    parser.add_argument("--repeat", type=int, default=1,
                        help="run the trials this many times, --base and this checkout taking "
                        "turns at going first (the machine's load drifts)")
    parser.add_argument("--twist", action="store_true",
                        help="a 20 Hz Twist beside it, priority real_time: its age")
    parser.add_argument("--twist-port", action="store_true",
                        help="the Twist on a port of its own (a socket of its own on each side)")
    args = parser.parse_args()
    global TWIST
    TWIST = args.twist or args.twist_port
    bench.next_domains = _domains
    if TWIST:
        bench.bringup_files = with_twist(bringup_files, args.twist_port)
    with tempfile.TemporaryDirectory(prefix="rosgate-fresh-") as tmp:
        folder = Path(tmp)
        probe = None
        if args.probe:
            (folder / "probe").mkdir()
            (folder / "probe" / "sitecustomize.py").write_text(PROBE)
            probe = folder / "ages"
            os.environ["PYTHONPATH"] = os.pathsep.join(
                filter(None, [str(folder / "probe"), os.environ.get("PYTHONPATH")]))
            os.environ["ROSGATE_PROBE_OUT"] = str(probe)
        checkouts = [Checkout()]
        if args.base:
            checkouts.insert(0, base_checkout(args.base, folder))
        sustained = args.sustained or sustained_rate(checkouts[-1], folder / "search")
        log(f"sustained: {sustained:,.0f} msg/s")
        rates = [("2x sustained", OVERLOAD * sustained)]
        if args.check:
            rates.append((f"{DROP_CHECK:g}x sustained", DROP_CHECK * sustained))
        for round_, (name, rate) in enumerate(
                [(name, rate) for _ in range(args.repeat) for name, rate in rates]):
            # back to back: the same load; in turns, first one, then the other first
            for checkout in checkouts[::-1] if round_ % 2 else checkouts:
                label = f"@{checkout.rev}" if checkout.rev else "this checkout"
                found = trial(checkout, folder / (checkout.rev or "here"), rate, args.seconds,
                              probe)
                print(f"== {SIZE.name} default file, best effort, {label}, {name} "
                      f"(round {round_ + 1}): "
                      f"{rate:,.0f} msg/s")
                for key, value in found.items():
                    print(f"  {key}: {value}")
                sys.stdout.flush()


if __name__ == "__main__":
    main()
