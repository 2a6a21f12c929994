"""A seeded schemathesis run against the real server: every operation, generated and example
requests with the admin token; no 5xx, every response conforming to its declared schema and
content type. (The long run of issue 11 is the same command with `-n 250`.)"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.e2e.conftest import TOKEN

pytestmark = pytest.mark.e2e

ST = Path(sys.executable).parent / "st"
CHECKS = ("not_a_server_error,status_code_conformance,content_type_conformance,"
          "response_schema_conformance,response_headers_conformance")


@pytest.mark.skipif(not ST.exists() and shutil.which("st") is None,
                    reason="schemathesis is not installed (make test installs it)")
def test_generated_requests_get_no_server_error_and_conform(server, http, fitted, tmp_path):
    st = str(ST) if ST.exists() else "st"
    run = subprocess.run(
        [st, "run", f"{server.url}/openapi.json", "--checks", CHECKS,
         "-H", f"Authorization: Bearer {TOKEN}", "-n", "15", "--seed", "1", "-w", "1",
         "--phases", "examples,coverage,fuzzing"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path, check=False)
    tail = run.stdout[-4000:]
    assert run.returncode == 0, tail
    assert "generated" in tail and "Server error" not in tail
