"""The fuzzing campaign: every target of targets.py under atheris, from its committed seeds.

    python tests/fuzz/campaign.py [--runs N] [--jobs J] [--only NAME,...] [--seed S]

``make fuzz`` runs 10^6 inputs per target; ``make test`` runs 10^4 (tests/fuzz/test_fuzz.py).
Each target runs in a process of its own (J at once), with new inputs in a scratch directory
(the committed corpus is only read), a limit of 100 ms of CPU per input, 1.5 GB of RSS per
process and 60 s per input. A finding is saved under tests/fuzz/findings/ (not committed):
fix it, then copy it to tests/fuzz/regressions/<target>/ so test_fuzz.py replays it forever.
Prints a table (runs, time, coverage, findings) and exits 1 when any target found something.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))

import targets  # noqa: E402

RSS_LIMIT_MB = 1536
TIMEOUT_S = 60  # libFuzzer's own per-input limit (whole seconds); fuzz.py enforces 100 ms of CPU


@dataclass
class Result:
    target: str
    runs: int
    seconds: float
    coverage: str
    findings: list[str]
    tail: str


def run_target(name: str, runs: int, seed: int | None, scratch: Path) -> Result:
    work = scratch / name
    work.mkdir(parents=True, exist_ok=True)
    findings = HERE / "findings"
    findings.mkdir(exist_ok=True)
    before = set(findings.glob(f"{name}-*"))
    command = [sys.executable, str(HERE / "fuzz.py"), name, f"-runs={runs}",
               f"-max_len={targets.MAX_LEN[name]}", f"-rss_limit_mb={RSS_LIMIT_MB}",
               f"-timeout={TIMEOUT_S}", f"-artifact_prefix={findings}/{name}-",
               "-print_final_stats=1", str(work), str(HERE / "corpus" / name)]
    if seed is not None:
        command.insert(3, f"-seed={seed}")
    start = time.monotonic()
    done = subprocess.run(command, capture_output=True, text=True)
    seconds = time.monotonic() - start
    output = done.stdout + done.stderr
    executed = re.search(r"stat::number_of_executed_units:\s*(\d+)", output)
    coverage = re.findall(r"cov: (\d+) ft: (\d+)", output)
    new = sorted(str(p.relative_to(HERE)) for p in set(findings.glob(f"{name}-*")) - before)
    if done.returncode != 0 and not new:
        new = [f"exit status {done.returncode} (no input saved)"]
    return Result(name, int(executed.group(1)) if executed else 0, seconds,
                  "cov {} ft {}".format(*coverage[-1]) if coverage else "?", new,
                  "\n".join(output.splitlines()[-40:]) if new else "")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1_000_000, help="inputs per target")
    parser.add_argument("--jobs", type=int, default=2, help="targets at once")
    parser.add_argument("--only", default="", help="comma-separated target names")
    parser.add_argument("--seed", type=int, default=None, help="libFuzzer's random seed")
    args = parser.parse_args()
    names = [n for n in targets.TARGETS if not args.only or n in args.only.split(",")]
    unknown = set(args.only.split(",")) - set(targets.TARGETS) - {""}
    if unknown:
        parser.error(f"no target {', '.join(sorted(unknown))} (there are: "
                     f"{', '.join(targets.TARGETS)})")
    start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="rosgate-fuzz-") as scratch, \
            ThreadPoolExecutor(args.jobs) as pool:
        results = list(pool.map(lambda n: run_target(n, args.runs, args.seed, Path(scratch)),
                                names))
    wall = time.monotonic() - start
    print("| target | inputs | seconds | inputs/s | coverage | findings |")
    print("|---|--:|--:|--:|---|---|")
    for r in results:
        rate = r.runs / r.seconds if r.seconds else 0
        print(f"| {r.target} | {r.runs:,} | {r.seconds:.0f} | {rate:,.0f} | {r.coverage} | "
              f"{', '.join(r.findings) or 'none'} |")
    print(f"\n{len(results)} targets, {sum(r.runs for r in results):,} inputs, "
          f"{wall / 60:.1f} min wall time with {args.jobs} at once")
    failed = [r for r in results if r.findings or r.runs < args.runs]
    for r in failed:
        print(f"\n== {r.target}: {r.runs:,} of {args.runs:,} inputs\n{r.tail}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
