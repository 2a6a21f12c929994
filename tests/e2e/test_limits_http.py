"""Issue 25, item 2, against the real server: the 6.5M-detection feedback upload of zeros
(under 1 MiB, 942 MiB inflated) is a 413 within a second, and neither it nor the same bytes
sent as a fit raise the server tree's memory (RSS sampled from /proc every 5 ms, and the
server's own high-water mark) by more than 64 MB."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from tests.e2e.conftest import ADMIN
from tests.zeros_npz import zeros_npz


def _tree(pid: int) -> list[int]:
    """`pid` and its descendants (from /proc/<pid>/task/*/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
    return out


def _kb(pid: int, field: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def tree_rss_mb(pid: int) -> float:
    """Resident memory of the process tree of `pid`, in MB."""
    return sum(_kb(p, "VmRSS") for p in _tree(pid)) / 1024


class Sampler:
    """The peak of `tree_rss_mb` while it runs (a thread sampling every 5 ms)."""

    def __init__(self, pid: int) -> None:
        self.pid, self.peak, self._stop = pid, 0.0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, tree_rss_mb(self.pid))
            time.sleep(0.005)

    def __enter__(self) -> Sampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


@pytest.fixture(scope="module")
def bomb() -> bytes:
    return zeros_npz(6_500_000)


@pytest.mark.parametrize("path", ["/v1/feedback", "/v1/fit"])
def test_the_zeros_bomb_is_413_before_it_inflates(server, http, bomb, path):
    pid = server.proc.pid
    assert http.get("/healthz").status_code == 200
    before, hwm = tree_rss_mb(pid), _kb(pid, "VmHWM") / 1024
    with Sampler(pid) as sampler:
        start = time.monotonic()
        r = http.post(path, headers=ADMIN, files={"dump": ("z.npz", bomb)})
        took = time.monotonic() - start
        time.sleep(0.05)
    rise = sampler.peak - before
    hwm_rise = _kb(pid, "VmHWM") / 1024 - hwm
    print(f"{path}: {len(bomb) // 1024} KiB upload -> {r.status_code} in {took:.3f} s, "
          f"tree RSS rise {rise:.1f} MB, server high-water mark rise {hwm_rise:.1f} MB")
    assert r.status_code == 413, r.text
    assert rise < 64 and hwm_rise < 64
