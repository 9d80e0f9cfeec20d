"""CPU per 1 MB image on each bridge: the default file, reliable, at a steady 20 images/s.

    .venv/bin/python bench/image_cpu.py [--seconds S] [--rounds N] [--base REV] [--profile]

The row "1 MB default file, reliable" of bench.py, measured for its CPU alone, with what a
bridge spends while idle taken apart: at 20 images/s, 1 ms per image is 2 % of a core, the same
order as an idle bridge's own timers and DDS's threads. Each round starts the case's four
processes fresh, waits until an image crosses, then reads each bridge's CPU time (utime + stime,
/proc) over ``--idle`` seconds of no traffic and over a trial of ``--seconds`` at 20 images/s:

* gross: the trial's CPU per image delivered (what bench.py reports);
* net: the same less the idle rate over the trial's length (what the images themselves cost);
* per thread: the trial's busiest threads of each bridge, net of their idle rate.

With ``--base REV`` every round runs REV's rosgate too (a temporary worktree with its own .venv,
as bench.py --base), alternating which goes first, so a machine loaded by others weighs on both
alike: compare the ratio, not the absolute numbers. ``--profile`` samples bridge A, then bridge
B with py-spy during an extra trial of this checkout's case, and prints each side's summary
(bench/profiling.py) to stdout.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import profiling
from processes import HERE_CHECKOUT, Checkout, thread_cpu_seconds

import bench

IMAGE = next(size for size in bench.SIZES if size.key == "1m")
ROUTE = bench.DEFAULT  # the default file, reliable
RATE = 20.0
TOP_THREADS = 6


def snapshot(case: bench.Case) -> tuple[float, dict[str, float], dict[str, dict]]:
    """(time, CPU seconds per bridge, per-thread CPU per bridge)."""
    sides = {"A": case.a, "B": case.b}
    cpu = {side: p.cpu() for side, p in sides.items() if p is not None}
    threads = {side: thread_cpu_seconds(p.pid) for side, p in sides.items() if p is not None}
    return time.monotonic(), cpu, threads


def thread_delta(before: dict, after: dict) -> dict[tuple[int, str], float]:
    out = {}
    for tid, (name, user, system) in after.items():
        _, user0, system0 = before.get(tid, (name, 0.0, 0.0))
        out[(tid, name)] = user + system - user0 - system0
    return out


def one_case(checkout: Checkout, folder: Path, seconds: float, idle: float,
             profile: bool) -> dict:
    route = replace(ROUTE, rev=checkout.rev)
    case = bench.Case(IMAGE, route, folder, checkout)
    with case:
        case.warm_up()
        t0, cpu0, th0 = snapshot(case)
        time.sleep(idle)
        t1, cpu1, th1 = snapshot(case)
        trial = case.trial(RATE, seconds)
        t2, cpu2, th2 = snapshot(case)
        result = {"label": case.label, "received": trial.received, "sent": trial.sent,
                  "p50": trial.p50_us, "p99": trial.p99_us}
        for side in ("A", "B"):
            idle_rate = (cpu1[side] - cpu0[side]) / (t1 - t0)
            gross = cpu2[side] - cpu1[side]
            net = gross - idle_rate * (t2 - t1)
            idle_threads = thread_delta(th0[side], th1[side])
            threads = thread_delta(th1[side], th2[side])
            per_thread = sorted(
                ((name, tid, (used - idle_threads.get((tid, name), 0.0) / (t1 - t0)
                              * (t2 - t1)) / max(trial.received, 1) * 1e3)
                 for (tid, name), used in threads.items()), key=lambda x: -x[2])
            result[side] = {"gross_ms": gross / max(trial.received, 1) * 1e3,
                            "net_ms": net / max(trial.received, 1) * 1e3,
                            "idle_pct": idle_rate * 100,
                            "threads": per_thread[:TOP_THREADS]}
        if profile:
            spec = bench.ProfileSpec(ROUTE.path, IMAGE.key, seconds, folder / "profiles")
            problems: list[str] = []
            for path in bench.profile(case, RATE, spec, trial, problems):
                print(path.read_text())
            for line in problems:
                print(line)
    return result


def show(result: dict) -> None:
    print(f"{result['label']}: {result['received']}/{result['sent']} images, p50 "
          f"{bench.ms(result['p50'])} ms, p99 {bench.ms(result['p99'])} ms")
    for side in ("A", "B"):
        r = result[side]
        threads = ", ".join(f"{name}[{tid}] {ms:.2f}" for name, tid, ms in r["threads"])
        print(f"  {side}: gross {r['gross_ms']:.2f} ms/image, net {r['net_ms']:.2f} ms/image "
              f"(idle {r['idle_pct']:.1f} % of a core); threads (net ms/image): {threads}")
    sys.stdout.flush()


def summary(results: dict[str, list[dict]]) -> None:
    print("\nmedians over rounds (ms of CPU per image):")
    medians = {}
    for label, rounds in results.items():
        medians[label] = {side: {kind: statistics.median(r[side][kind] for r in rounds)
                                 for kind in ("gross_ms", "net_ms")} for side in ("A", "B")}
        m = medians[label]
        print(f"  {label}: A gross {m['A']['gross_ms']:.2f} net {m['A']['net_ms']:.2f}; "
              f"B gross {m['B']['gross_ms']:.2f} net {m['B']['net_ms']:.2f} "
              f"({len(rounds)} rounds)")
    if len(medians) == 2:
        (here, mine), (base, theirs) = medians.items()
        for side in ("A", "B"):
            for kind in ("gross_ms", "net_ms"):
                print(f"  {side} {kind[:-3]}: {here} / {base} = "
                      f"{mine[side][kind] / theirs[side][kind]:.2f}x")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=6.0, help="each trial (default 6)")
    parser.add_argument("--idle", type=float, default=3.0,
                        help="seconds of no traffic the idle rate is read over (default 3)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    parser.add_argument("--base", metavar="REV", help="also measure REV's rosgate")
    parser.add_argument("--profile", action="store_true",
                        help="py-spy both bridges of this checkout in the first round")
    args = parser.parse_args()
    results: dict[str, list[dict]] = {}
    with ExitStack() as stack:
        checkouts = [HERE_CHECKOUT]
        if args.base:
            checkouts.append(bench.base_checkout(args.base, stack))
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="rosgate-image-")))
        for n in range(args.rounds):
            order = checkouts if n % 2 == 0 else checkouts[::-1]
            for checkout in order:
                folder = tmp / f"round{n}-{checkout.rev or 'here'}"
                result = one_case(checkout, folder, args.seconds, args.idle,
                                  args.profile and n == 0 and checkout is HERE_CHECKOUT)
                results.setdefault(result["label"], []).append(result)
                show(result)
    summary(results)
    return 0


if __name__ == "__main__":
    if not profiling.PYSPY.exists():
        print("(py-spy is not installed: --profile will fail)", file=sys.stderr)
    sys.exit(main())
