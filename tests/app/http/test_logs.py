"""Issue 25, item 7: `app.http.logs.log_config` sends the detcal.* loggers to stderr with levels,
as text or JSON lines, and a configured token never reaches the log (run in a fresh
interpreter: the configuration is process-wide)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
SECRET = "s3cret-admin-token-for-the-log-test"

SCRIPT = """
import logging, logging.config, sys
from app.http.logs import log_config
logging.config.dictConfig(log_config(sys.argv[1], sys.argv[2]))
log = logging.getLogger("detcal.jobs")
log.debug("a debug line")
log.info("fit job %s: %s landed", "abc", "lidar@2")
logging.getLogger("detcal.http").warning("refused with Bearer %s", sys.argv[3])
try:
    1 / 0
except ZeroDivisionError:
    logging.getLogger("detcal.store").exception("boom")
"""


def _run(level: str, fmt: str) -> list[str]:
    env = {**os.environ, "DETCAL_ADMIN_TOKEN": SECRET}
    proc = subprocess.run([sys.executable, "-c", SCRIPT, level, fmt, SECRET], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout == ""
    return proc.stderr.splitlines()


def test_json_lines_with_levels_and_no_token() -> None:
    lines = [json.loads(line) for line in _run("info", "json") if line.startswith("{")]
    assert [(r["level"], r["logger"]) for r in lines] == [
        ("INFO", "detcal.jobs"), ("WARNING", "detcal.http"), ("ERROR", "detcal.store")]
    assert lines[0]["message"] == "fit job abc: lidar@2 landed"
    assert "<token>" in lines[1]["message"] and SECRET not in json.dumps(lines)
    assert "ZeroDivisionError" in lines[2]["exception"]
    assert lines[0]["time"].endswith("+00:00")


@pytest.mark.parametrize(("level", "seen"), [("debug", 4), ("warning", 2), ("error", 1)])
def test_text_lines_follow_the_level(level: str, seen: int) -> None:
    lines = [line for line in _run(level, "text") if " detcal." in line]
    assert len(lines) == seen, lines
    assert all(SECRET not in line for line in lines)
