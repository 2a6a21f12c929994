"""A server's process tree read from /proc (Linux): its members, their resident memory, and
a peak-memory probe that resets each member's high-water mark (`clear_refs` 5) and reads it
back after a request."""

from __future__ import annotations

import os
from pathlib import Path

PROC = Path("/proc")


def _ppid(pid: int) -> int | None:
    try:
        stat = (PROC / str(pid) / "stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[1])


def tree(root: int) -> list[int]:
    """`root` and every live descendant of it (zombies included)."""
    parents: dict[int, list[int]] = {}
    for entry in PROC.iterdir():
        if entry.name.isdigit():
            ppid = _ppid(int(entry.name))
            if ppid is not None:
                parents.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        if (PROC / str(pid)).exists():
            out.append(pid)
        todo.extend(parents.get(pid, []))
    return out


def alive(pid: int) -> bool:
    """Whether `pid` exists and is not a zombie."""
    try:
        stat = (PROC / str(pid) / "stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _kib(pid: int, key: str) -> int:
    try:
        for line in (PROC / str(pid) / "status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def rss_mb(pids: list[int]) -> float:
    """Resident memory of `pids` together, MB."""
    return sum(_kib(p, "VmRSS") for p in pids) / 1024


class PeakProbe:
    """Peak resident memory of a fixed set of processes across a stretch of time: `start()`
    resets each high-water mark, `rise_mb()` is the sum of the marks since then minus the
    resident memory at `start()` (an upper bound of the tree's peak rise)."""

    def __init__(self, pids: list[int]) -> None:
        self.pids = pids
        self.before = 0.0

    def start(self) -> None:
        """Reset the marks and note the current resident memory."""
        for pid in self.pids:
            try:
                with open(PROC / str(pid) / "clear_refs", "w") as f:
                    f.write("5")
            except OSError:
                pass
        self.before = rss_mb(self.pids)

    def rise_mb(self) -> float:
        """The peak rise since `start()`, MB."""
        return sum(_kib(p, "VmHWM") for p in self.pids) / 1024 - self.before


def detcal_processes_of(pids: list[int]) -> list[int]:
    """Those of `pids` still alive (not zombies)."""
    return [p for p in pids if alive(p) and p != os.getpid()]
