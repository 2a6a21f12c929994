"""`detcal serve` on a port another process holds: one clear error, exit status 1, and no
"serving on" line before it."""

from __future__ import annotations

import socket
import subprocess

import pytest

from tests.e2e.conftest import ROOT, _detcal

pytestmark = pytest.mark.e2e


def test_a_busy_port_is_one_clear_error(tmp_path):
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        run = subprocess.run([*_detcal(), "serve", "--port", str(port), "--host", "127.0.0.1",
                              "--data-dir", str(tmp_path / "data")], cwd=ROOT,
                             capture_output=True, text=True, timeout=60)
    assert run.returncode == 1, (run.stdout, run.stderr)
    assert "serving on" not in run.stdout + run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "already in use" in lines[0], run.stderr
    assert f"http://127.0.0.1:{port}/" in lines[0] and "--port" in lines[0]
