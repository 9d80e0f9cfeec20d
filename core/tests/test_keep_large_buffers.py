"""``rosgate run`` asks glibc's malloc to keep megabyte buffers in its heaps: a 4 MB block is then
not a fresh mapping (faulted in a page at a time on every use), and the environment's own
MALLOC_*_THRESHOLD_ is left to win."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys

import pytest

# in a fresh interpreter: a process's first large block shows malloc's default at work
PROBE = """
import ctypes, sys
class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost"
                .split()]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Info
from rosgate.cli import keep_large_buffers
if sys.argv[1] == "keep":
    keep_large_buffers()
before = libc.mallinfo2().hblkhd
block = bytearray(4 * 1024 * 1024)
print(libc.mallinfo2().hblkhd - before)
"""

glibc = hasattr(ctypes.CDLL(None), "mallinfo2")


def mapped(mode: str, **env: str) -> int:
    """Bytes of mmapped blocks a 4 MB bytearray added, in a fresh interpreter."""
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True,
                         env={**os.environ, **env}, check=True, timeout=60)
    return int(out.stdout)


@pytest.mark.skipif(not glibc, reason="glibc's malloc only")
def test_a_large_block_comes_from_the_heap_once_the_bridge_keeps_buffers():
    assert mapped("default") >= 4 * 1024 * 1024  # glibc's default: a fresh mapping
    assert mapped("keep") == 0


@pytest.mark.skipif(not glibc, reason="glibc's malloc only")
def test_the_environment_s_own_malloc_settings_win():
    assert mapped("keep", MALLOC_MMAP_THRESHOLD_="131072") >= 4 * 1024 * 1024
