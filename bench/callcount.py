"""Run a program with every Python thread under cProfile, and say on request how many times each
function was called so far, per thread (bench/cpu_counts.py reads it around a trial).

    python bench/callcount.py FIFO -m rosgate run FILE     # or: FIFO path/to/script.py ARGS

A line ``PATH`` written to the named pipe ``FIFO`` makes it write ``PATH``: JSON, thread name ->
function -> calls (Python functions as ``file:line(name)``, C ones as cProfile names them). The
thread that reads the pipe is not profiled and blocks on it: it costs the program nothing between
requests. Counts do not depend on the machine's load; times under cProfile mean little.
"""

from __future__ import annotations

import cProfile
import json
import os
import runpy
import sys
import threading
from typing import Any

_profiles: dict[str, cProfile.Profile] = {}
_lock = threading.Lock()


def _name(code: Any) -> str:
    if isinstance(code, str):
        return code
    path = code.co_filename
    for marker in ("/src/", "/site-packages/", "/lib/python3"):
        if marker in path:
            path = path.split(marker, 1)[1]
            break
    return f"{path}:{code.co_firstlineno}({code.co_name})"


def _start(*_: Any) -> None:
    """The first profile event of a new thread: a profiler of its own replaces this hook."""
    profile = cProfile.Profile()
    thread = threading.current_thread()
    with _lock:
        _profiles[f"{thread.name}#{thread.native_id}"] = profile
    profile.enable()


def _snapshot() -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    with _lock:
        profiles = dict(_profiles)
    for thread, profile in profiles.items():
        counts: dict[str, int] = {}
        for entry in profile.getstats():
            key = _name(entry.code)
            counts[key] = counts.get(key, 0) + entry.callcount
        out[thread] = counts
    return out


def _serve(fifo: str) -> None:
    sys.setprofile(None)
    while True:
        with open(fifo) as requests:
            for line in requests:
                path = line.strip()
                if path:
                    tmp = path + ".tmp"
                    with open(tmp, "w") as out:
                        json.dump(_snapshot(), out)
                    os.replace(tmp, path)


def main() -> None:
    fifo, *argv = sys.argv[1:]
    threading.Thread(target=_serve, args=(fifo,), name="callcount", daemon=True).start()
    threading.setprofile(_start)
    _start()
    if argv[0] == "-m":
        sys.argv = [argv[1], *argv[2:]]
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv = argv
        sys.path.insert(0, os.path.dirname(os.path.abspath(argv[0])))
        runpy.run_path(argv[0], run_name="__main__")


if __name__ == "__main__":
    main()
