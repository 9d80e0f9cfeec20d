"""What a process holds, read from /proc: file descriptors, threads, memory, CPU time and the
ports it has bound. The attack tests and the soak compare these before and after."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

_SOCKET = re.compile(r"socket:\[(\d+)\]")
_TCP_LISTEN = "0A"


@dataclass(frozen=True)
class Snapshot:
    fds: int
    threads: int
    rss_mb: float
    cpu_s: float
    ports: frozenset[tuple[str, int]]  # ("tcp", port) listening, ("udp", port) bound


class Resources:
    """One process's resources, by pid."""

    def __init__(self, pid: int):
        self.pid = pid

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.pid}/fd"))

    def threads(self) -> int:
        return len(os.listdir(f"/proc/{self.pid}/task"))

    def rss_mb(self) -> float:
        with open(f"/proc/{self.pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        return 0.0

    def cpu_s(self) -> float:
        """User + system CPU seconds so far."""
        with open(f"/proc/{self.pid}/stat") as stat:
            fields = stat.read().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def ports(self) -> frozenset[tuple[str, int]]:
        """TCP ports it listens on and UDP ports it has bound (IPv4 and IPv6)."""
        inodes = set()
        for fd in os.listdir(f"/proc/{self.pid}/fd"):
            try:
                match = _SOCKET.fullmatch(os.readlink(f"/proc/{self.pid}/fd/{fd}"))
            except OSError:  # closed meanwhile
                continue
            if match:
                inodes.add(match.group(1))
        found = set()
        for proto in ("tcp", "tcp6", "udp", "udp6"):
            try:
                with open(f"/proc/{self.pid}/net/{proto}") as table:
                    next(table)
                    for line in table:
                        fields = line.split()
                        local, state, inode = fields[1], fields[3], fields[9]
                        if inode in inodes and (proto.startswith("udp") or state == _TCP_LISTEN):
                            found.add((proto[:3], int(local.rpartition(":")[2], 16)))
            except FileNotFoundError:
                continue
        return frozenset(found)

    def snapshot(self) -> Snapshot:
        return Snapshot(self.fds(), self.threads(), self.rss_mb(), self.cpu_s(), self.ports())
