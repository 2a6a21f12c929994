"""A cheap "has anything been committed since?" check of a SQLite database, for caches of what
the database says (the active version of a profile) shared by several processes.

SQLite's `PRAGMA data_version` changes, on the connection that asks, whenever another
connection (of this process or any other) commits to the database. Asked on a connection of
its own that never writes, it changes on every commit. It costs microseconds, where reading
the active pointer through the ORM costs ~0.13 ms on every calibrate request.
"""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path


class CommitMarker:
    """`value()`: a number that differs after any commit to the database file `path`."""

    def __init__(self, path: Path) -> None:
        self._conn = sqlite3.connect(path, check_same_thread=False)   # only ever reads
        self._lock = threading.Lock()

    def value(self) -> int:
        with self._lock:
            return int(self._conn.execute("PRAGMA data_version").fetchone()[0])

    def close(self) -> None:
        with self._lock:
            self._conn.close()
