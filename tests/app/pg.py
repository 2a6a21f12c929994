"""A throwaway Postgres cluster for the store tests: initdb in a temp dir, pg_ctl on loopback.

The cluster listens on 127.0.0.1 only (no Unix socket), trusts local TCP connections, runs
without fsync (its data is thrown away), and is removed at teardown. As root it runs as the
`postgres` OS user (initdb refuses root). Without the server binaries the tests skip locally
and fail under CI (the `CI` environment variable), which must exercise Postgres.

One cluster per test process is shared by every module that asks for it (`acquire()` /
`release()` count the users). Each test gets an empty schema of one shared database from
`fresh_url()`, selected by the URL's `search_path`: as isolated as a new database for the
store, in milliseconds instead of a CREATE DATABASE's ~0.3 s.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path

import pytest

PG_USER = "postgres"
TEST_DB = "detcal_test"
_SETTINGS = ("listen_addresses=127.0.0.1", "unix_socket_directories=", "fsync=off",
             "synchronous_commit=off", "full_page_writes=off", "max_connections=50",
             "shared_buffers=16MB", "max_wal_size=256MB")


def bin_dir() -> Path | None:
    """The directory holding `initdb` and `pg_ctl`: on PATH, else Debian's newest version."""
    found = shutil.which("pg_ctl")
    if found:
        real = Path(found).resolve().parent
        if (real / "initdb").exists():
            return real
    versions = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"),
                      key=lambda p: int(p.parts[-3]) if p.parts[-3].isdigit() else 0)
    return versions[-1].parent if versions else None


def unavailable(reason: str) -> None:
    """Skip the test with `reason`, or fail it when running under CI."""
    if os.environ.get("CI"):
        pytest.fail(f"Postgres tests must run in CI: {reason}", pytrace=False)
    pytest.skip(f"Postgres tests skipped: {reason} (install Debian's `postgresql`: "
                "make postgres)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresCluster:
    """A started throwaway cluster; `url(db)` is a SQLAlchemy psycopg URL to database `db`."""

    def __init__(self, binaries: Path) -> None:
        self.binaries = binaries
        self.as_root = os.geteuid() == 0
        self.dir = Path(tempfile.mkdtemp(prefix="detcal-pg-"))
        self.data = self.dir / "data"
        self.log = self.dir / "server.log"
        self.port = 0
        if self.as_root:
            user = pwd.getpwnam(PG_USER)
            os.chown(self.dir, user.pw_uid, user.pw_gid)

    def _run(self, *args: str) -> subprocess.CompletedProcess[str]:
        cmd = [str(self.binaries / args[0]), *args[1:]]
        if self.as_root:
            cmd = ["runuser", "-u", PG_USER, "--", *cmd]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)

    def start(self) -> None:
        """initdb, then pg_ctl start on a free loopback port (a few tries if one is taken)."""
        done = self._run("initdb", "-D", str(self.data), "-U", PG_USER, "--auth=trust",
                         "--no-sync", "--no-instructions", "-E", "UTF8", "--locale=C")
        if done.returncode != 0:
            raise RuntimeError(f"initdb failed: {done.stderr or done.stdout}")
        for _ in range(3):
            self.port = _free_port()
            options = " ".join(f"-c {s}" for s in (*_SETTINGS, f"port={self.port}"))
            done = self._run("pg_ctl", "start", "-w", "-t", "30", "-D", str(self.data),
                             "-l", str(self.log), "-o", options)
            if done.returncode == 0:
                self._sql(f"CREATE DATABASE {TEST_DB} TEMPLATE template0", "postgres")
                return
        log = self.log.read_text()[-2000:] if self.log.exists() else ""
        raise RuntimeError(f"pg_ctl start failed: {done.stderr or done.stdout}\n{log}")

    def stop(self) -> None:
        """Stop the server (immediately: the data is thrown away) and remove its directory."""
        if (self.data / "postmaster.pid").exists():
            self._run("pg_ctl", "stop", "-w", "-m", "immediate", "-D", str(self.data))
        shutil.rmtree(self.dir, ignore_errors=True)

    def _sql(self, statement: str, database: str = TEST_DB) -> None:
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user=PG_USER, dbname=database,
                             autocommit=True) as conn:
            conn.execute(statement)

    def fresh_url(self, driver: str = "postgresql+psycopg") -> str:
        """SQLAlchemy URL of a new, empty schema (the connection's `search_path`)."""
        schema = f"t_{uuid.uuid4().hex[:12]}"
        self._sql(f"CREATE SCHEMA {schema}")
        return (f"{driver}://{PG_USER}@127.0.0.1:{self.port}/{TEST_DB}"
                f"?options=-csearch_path%3D{schema}")


_shared: PostgresCluster | None = None
_users = 0


def acquire() -> PostgresCluster:
    """The process's cluster, started on first use; skips (or fails under CI) if impossible."""
    global _shared, _users
    if _shared is None:
        try:
            import psycopg  # noqa: F401
        except ImportError:
            unavailable("the psycopg driver is not installed")
        binaries = bin_dir()
        if binaries is None:
            unavailable("no Postgres server binaries (pg_ctl, initdb) found")
        if os.geteuid() == 0:
            try:
                pwd.getpwnam(PG_USER)
            except KeyError:
                unavailable(f"running as root and there is no {PG_USER!r} OS user")
        cluster = PostgresCluster(binaries)
        try:
            cluster.start()
        except BaseException:
            cluster.stop()
            raise
        _shared = cluster
    _users += 1
    return _shared


def release() -> None:
    """Drop one user of the cluster; the last one stops and removes it."""
    global _shared, _users
    _users -= 1
    if _users <= 0 and _shared is not None:
        _shared.stop()
        _shared, _users = None, 0
