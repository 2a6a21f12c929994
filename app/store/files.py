"""The store's files: private modes, the dumps directory's lock, partial uploads, liveness locks.

Everything detcal keeps on disk is private to the service's user: directories 0700, files
0600 (an existing store from an older detcal is tightened when opened). Uploads are written
to `.upload-*` temporary files under a shared lock on `dumps/.lock`; the clean-up takes it
exclusively, so a `.upload-*` it finds then belongs to a writer that died. Both rely on
`flock`, which works across processes (and containers) sharing a local directory, and across
hosts only where the filesystem supports it (NFS with its lock manager).
"""

from __future__ import annotations

import fcntl
import os
import re
import time
from collections.abc import Collection, Iterator
from contextlib import contextmanager
from pathlib import Path

DIR_MODE = 0o700
FILE_MODE = 0o600
UPLOAD_PREFIX = ".upload-"
LOCK_FILE = ".lock"
DUMP_NAME = re.compile(r"^[0-9a-f]{64}$")


def private_dir(path: Path) -> Path:
    """Make `path` 0700, creating it and its missing parents 0700 (a parent that exists
    keeps its mode); `path`."""
    missing = [p for p in (path, *path.parents) if not p.exists()]
    for directory in reversed(missing):
        directory.mkdir(mode=DIR_MODE, exist_ok=True)
        directory.chmod(DIR_MODE)               # whatever the umask
    if path.stat().st_mode & 0o777 != DIR_MODE:
        path.chmod(DIR_MODE)
    return path


def tighten(path: Path) -> bool:
    """Drop group and other permissions of `path` if it exists; True if it changed."""
    try:
        mode = path.stat().st_mode & 0o777
    except FileNotFoundError:
        return False
    if mode & 0o077 == 0:
        return False
    path.chmod(mode & 0o700)
    return True


def private_sqlite(database: Path) -> None:
    """A SQLite database file created 0600 before SQLite opens it (its `-wal` and `-shm`
    files then get the same mode), or an existing one and its companions tightened."""
    try:
        os.close(os.open(database, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE))
    except FileExistsError:
        pass
    for suffix in ("", "-wal", "-shm", "-journal"):
        tighten(database.with_name(database.name + suffix))


@contextmanager
def flocked(path: Path, *, exclusive: bool, wait_s: float | None = None) -> Iterator[bool]:
    """Hold `flock` on `path` (created 0600) for the block; yields False, holding nothing,
    when `wait_s` is given and the lock was not free within it (None: wait as long as needed).
    """
    fd = os.open(path, os.O_RDWR | os.O_CREAT, FILE_MODE)
    try:
        yield _lock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH, wait_s)
    finally:
        os.close(fd)


def _lock(fd: int, op: int, wait_s: float | None) -> bool:
    if wait_s is None:
        fcntl.flock(fd, op)
        return True
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, op | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


def is_locked(path: Path) -> bool | None:
    """Whether some open file holds `flock` on `path` (None: there is no such file)."""
    try:
        fd = os.open(path, os.O_RDWR)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


class InstanceLock:
    """A lock file that says "this process is alive": held from `acquire()` to `release()`
    (or the process's death, when the kernel drops it), named after an instance id in `dir`.

    `alive(instance)` tells another process, without any timeout, whether that instance still
    holds its lock; None when it has no lock file here (another host, or never existed).
    """

    def __init__(self, directory: Path, instance: str) -> None:
        self.dir, self.instance = directory, instance
        self._fd: int | None = None

    def path(self, instance: str) -> Path:
        """The lock file of `instance`."""
        return self.dir / (re.sub(r"[^A-Za-z0-9._-]", "_", instance) + ".lock")

    def acquire(self) -> None:
        """Create and lock the file; it appears under its name only once locked."""
        private_dir(self.dir)
        tmp = self.dir / f".{os.getpid()}-{time.monotonic_ns()}.tmp"
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL, FILE_MODE)
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.replace(tmp, self.path(self.instance))
        self._fd = fd

    def release(self) -> None:
        """Remove the file and drop the lock."""
        if self._fd is None:
            return
        self.path(self.instance).unlink(missing_ok=True)
        os.close(self._fd)
        self._fd = None

    def alive(self, instance: str) -> bool | None:
        if instance == self.instance:
            return self._fd is not None
        locked = is_locked(self.path(instance))
        return None if locked is None else locked

    def sweep(self, keep: Collection[str] = ()) -> int:
        """Remove the lock files of dead instances, except those of `keep` (and temporaries
        of creators that died); how many lock files."""
        kept = {self.path(i) for i in (*keep, self.instance)}
        n = 0
        for path in self.dir.glob("*.lock"):
            if path not in kept and is_locked(path) is False:
                path.unlink(missing_ok=True)
                n += 1
        for path in self.dir.glob(".*.tmp"):
            if time.time() - _mtime(path) > 60 and is_locked(path) is False:
                path.unlink(missing_ok=True)
        return n


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except FileNotFoundError:
        return time.time()
