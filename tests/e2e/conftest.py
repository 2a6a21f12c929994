"""A real `detcal serve` process on a free loopback port, shared by the end-to-end tests.

At most two server processes start per session: the first, and one restart on the same data
directory (test_server's persistence check).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "e2e-admin-token-abcdefghijklmnop"
ADMIN = {"Authorization": f"Bearer {TOKEN}"}


def _detcal() -> list[str]:
    exe = ROOT / ".venv" / "bin" / "detcal"
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-m", "app.cli.main"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """One `detcal serve` process (restartable on the same port and data directory)."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None
        self.starts = 0
        self.log = data_dir.parent / "server.log"

    #: Extra `detcal serve` arguments, the admin token it is started with (None: it writes
    #: its own, as `make run` does) and the path that says it is up.
    serve_args: tuple[str, ...] = ()
    token_env: str | None = TOKEN
    ready_path = "/healthz"

    def start(self, timeout_s: float = 60.0) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        for name in ("DETCAL_ADMIN_TOKEN", "DETCAL_DATABASE_URL", "DETCAL_DATA_DIR"):
            env.pop(name, None)
        if self.token_env is not None:
            env["DETCAL_ADMIN_TOKEN"] = self.token_env
        cmd = [*_detcal(), "serve", "--host", "127.0.0.1", "--port", str(self.port),
               "--data-dir", str(self.data_dir), "--log-level", "warning", *self.serve_args]
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=self.log.open("a"),
                                     stderr=subprocess.STDOUT)
        self.starts += 1
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"detcal serve exited: {self.log.read_text()[-2000:]}")
            try:
                if httpx.get(f"{self.url}{self.ready_path}", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"detcal serve did not come up: {self.log.read_text()[-2000:]}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc = None

    def restart(self) -> None:
        self.stop()
        self.start()


def serving(srv: Server) -> Iterator[Server]:
    """Start `srv`, yield it, stop it (the body of a server fixture)."""
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The running server (started once per session)."""
    yield from serving(Server(tmp_path_factory.mktemp("e2e") / "data"))


@pytest.fixture(scope="session")
def http(server: Server) -> Iterator[httpx.Client]:
    """An httpx client for the server (follows its restarts: same base URL)."""
    with httpx.Client(base_url=server.url, timeout=30.0) as c:
        yield c


@pytest.fixture(scope="session")
def dump():
    """The synthetic validation dump the e2e fits use (sigmoid, 10 classes, det_cov)."""
    from calibrators.data import synthetic_dump

    return synthetic_dump(n_frames=40, seed=1)


@pytest.fixture(scope="session")
def dump_npz(dump, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """`dump` saved as NPZ v1 with calibrators.io.save_dump."""
    from calibrators.io import save_dump

    path = tmp_path_factory.mktemp("dump") / "val.npz"
    save_dump(path, dump)
    return path.read_bytes()


def wait_job(http: httpx.Client, job_id: str, timeout_s: float = 120.0) -> dict:
    """Poll a job until it is succeeded or failed."""
    deadline = time.monotonic() + timeout_s
    seen = []
    while time.monotonic() < deadline:
        body = http.get(f"/v1/jobs/{job_id}", headers=ADMIN).json()
        seen.append(body["state"])
        if body["state"] in ("succeeded", "failed"):
            body["_states_seen"] = seen
            return body
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish: {seen[-5:]}")


@pytest.fixture(scope="session")
def fitted(http: httpx.Client, dump_npz: bytes) -> dict:
    """The first fit of profile `lidar` on the server (the finished job)."""
    r = http.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", dump_npz)},
                  data={"name": "lidar", "holdout": "0.25"})
    assert r.status_code == 202, r.text
    return wait_job(http, r.json()["job_id"])


@pytest.fixture(scope="session")
def admin() -> dict[str, str]:
    """Headers carrying the server's admin token."""
    return dict(ADMIN)


@pytest.fixture(scope="session")
def wait():
    """`wait(http, job_id)`: poll a fit job until it finishes."""
    return wait_job


@pytest.fixture
def own_server(tmp_path: Path) -> Iterator[Server]:
    """A server of this test alone on a fresh data directory (one it may kill and restart)."""
    yield from serving(Server(tmp_path / "data"))


@pytest.fixture(scope="session")
def large_dump_npz(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A synthetic dump large enough that its fit runs for a few tenths of a second (400
    frames, ~8 MB): long enough to act while a job runs."""
    from calibrators.data import synthetic_dump
    from calibrators.io import save_dump

    path = tmp_path_factory.mktemp("dump") / "large.npz"
    save_dump(path, synthetic_dump(n_frames=400, seed=2))
    return path.read_bytes()
