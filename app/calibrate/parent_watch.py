"""Child processes of the server (calibrate workers) that die with it, even when it is killed
with SIGKILL and has no chance to stop them.

The same goes for the uvicorn worker processes of `detcal serve --workers N`
(`die_with_supervisor`, called as the app starts). Two mechanisms, either enough on its own:

- Linux's parent-death signal (`prctl(PR_SET_PDEATHSIG, SIGKILL)`): the kernel kills the
  child when the thread that started it ends. The calibrate pool is started from the server's
  event-loop thread, which lives as long as the server.
- A daemon thread that polls the parent's pid (`os.getppid()` changes when the child is
  re-parented to init or a subreaper) and ends the process: the fallback where `prctl` is
  missing (not Linux) or the starting thread ended first.

The multiprocessing resource tracker needs neither: it exits when the last holder of its pipe
(the server and its workers) is gone (`tests/e2e/test_kill9_pool.py` checks the whole tree).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
import threading

PR_SET_PDEATHSIG = 1
POLL_S = 0.5


def die_with_parent(parent_pid: int, poll_s: float = POLL_S) -> bool:
    """Make this process end when `parent_pid` (its parent) does; True when the kernel's
    parent-death signal is set (Linux), False when only the polling thread watches. Exits at
    once when the parent is already gone."""
    armed = _set_pdeathsig()
    if os.getppid() != parent_pid:   # the parent died before the signal was armed
        os._exit(1)
    thread = threading.Thread(target=_watch, args=(parent_pid, poll_s), daemon=True,
                              name="detcal-parent-watch")
    thread.start()
    return armed


def die_with_supervisor() -> bool:
    """In a process started by multiprocessing (a `uvicorn --workers N` worker), end it when
    its parent, the supervisor, ends; True when armed. A server started any other way keeps
    running when whatever launched it exits."""
    parent = multiprocessing.parent_process()
    if parent is None or parent.pid is None:
        return False
    die_with_parent(parent.pid)
    return True


def _set_pdeathsig() -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent_pid: int, poll_s: float) -> None:
    event = threading.Event()
    while not event.wait(poll_s):
        if os.getppid() != parent_pid:
            os._exit(1)
