"""The shell steps of the docs the README tour test runs (tests/e2e/test_docs_tour.py): the
commands of README.md's "A 5-minute tour" section and of docs/api.md's curl examples, split one
command at a time (`tour_steps`), and each run through bash against a server (`run_step`,
`watch_job`). What a step may be is explicit (`STEP_KINDS`), and so is everything the test
changes in one (`SUBSTITUTIONS`), the input files it provides (`INPUTS`) and the commands it
skips (`SKIPPED`)."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tests.docs.test_examples import fenced_blocks
from tests.e2e.conftest import ROOT

README = ROOT / "README.md"
API_MD = ROOT / "docs" / "api.md"
TOUR_HEADING = "## A 5-minute tour"
SHELL_LANGS = ("sh", "bash", "shell")
NUSC_SAMPLE_FRAMES = 10     # results_nusc.json: the first frames of val.npz (under 8 MiB)
SHIPPED_DUMP = ROOT / "detectors" / "data" / "lidar_val.npz"


@dataclass
class Tour:
    """What later steps need from earlier ones."""

    url: str
    token: str
    workdir: Path
    job_id: str | None = None                   # the latest POST /v1/fit's job
    step1: Step | None = None                   # the README tour's first /v1/calibrate
    ran: list[str] = field(default_factory=list)


def _latest_job(t: Tour) -> str:
    assert t.job_id, "a step names a job before any POST /v1/fit returned one"
    return t.job_id


# Text in a step -> what it becomes. Each must be used by some step (a stale one fails).
SUBSTITUTIONS: dict[str, Callable[[Tour], str]] = {
    "http://127.0.0.1:8000": lambda t: t.url,            # `export DETCAL=...`: the test server
    "detectors/data/lidar_val.npz": lambda t: str(SHIPPED_DUMP),   # run from the clone's root
    "<job_id>": _latest_job,                             # README step 4: the fit just queued
    "6f1c0b9e2d4a4c4f9a3e8d7b1c2a5f60": _latest_job,     # docs/api.md: an example job id
}

# Commands that cannot run headless: the first word -> why it is skipped.
SKIPPED = {
    "xdg-open": "opens a browser; tests/e2e/test_dashboard.py renders the dashboard",
    "open": "opens a browser; tests/e2e/test_dashboard.py renders the dashboard",
}

# Routes whose answer is not JSON: path -> the content type it has instead.
NON_JSON = {"/metrics": "text/plain"}


def _nusc_from_val(workdir: Path, results: str, gt: str | None, frames: int | None) -> None:
    from calibrators import load_dump, save_nuscenes

    dump = load_dump(SHIPPED_DUMP)
    if frames is not None:
        dump = dump.select_frames(np.arange(dump.n_frames) < frames)
    save_nuscenes(dump, workdir / results, None if gt is None else workdir / gt)


def _coco_pair(workdir: Path) -> None:
    """docs/api.md's 2-D fit: a synthetic COCO results file and its instances."""
    from calibrators.boxes2d import synthetic_coco

    results, instances = synthetic_coco(n_images=400, seed=0)
    (workdir / "coco_results.json").write_text(json.dumps(results))
    (workdir / "coco_instances.json").write_text(json.dumps(instances))


# Input files the doc examples read and no earlier step writes: name -> how to make it.
INPUTS: dict[str, Callable[[Path], None]] = {
    "coco_results.json": _coco_pair,
    "coco_instances.json": _coco_pair,
    "val.npz": lambda w: shutil.copyfile(SHIPPED_DUMP, w / "val.npz"),
    "results_nusc.json": lambda w: _nusc_from_val(w, "results_nusc.json", None,
                                                  NUSC_SAMPLE_FRAMES),
    "val_nusc.json": lambda w: _nusc_from_val(w, "val_nusc.json", "val_nusc_gt.json", None),
    "val_nusc_gt.json": lambda w: _nusc_from_val(w, "val_nusc.json", "val_nusc_gt.json", None),
}

# bash around every step: errors stop it, and curl shows them, fails on a status >= 400 (with
# the body) and writes the response headers where the test reads the status and content type.
PREAMBLE = """set -euo pipefail
curl() { command curl --show-error --fail-with-body --dump-header "$DOCTOUR_HEADERS" "$@"; }
"""


# -- parsing -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Step:
    """One shell command of a doc: where it is, its text as written, and its kind."""

    where: str
    text: str

    @property
    def words(self) -> list[str]:
        return shlex.split(self.text, comments=True)

    @property
    def kind(self) -> str:
        return STEP_KINDS.get(self.words[0], "unknown")

    @property
    def route(self) -> str:
        """The path of the `$DETCAL` URL a curl step calls (no query)."""
        urls = [w for w in self.words if w.startswith("$DETCAL")]
        assert len(urls) == 1, f"{self.where}: expected one $DETCAL URL in {self.text!r}"
        return urls[0][len("$DETCAL"):].split("?")[0] or "/"

    @property
    def output_file(self) -> str | None:
        words = self.words
        for i, w in enumerate(words[:-1]):
            if w in ("-o", "--output"):
                return words[i + 1]
        return None


STEP_KINDS = {"export": "export", "curl": "curl", ".venv/bin/detcal": "detcal",
              "detcal": "detcal", **{name: "skip" for name in SKIPPED}}


def split_commands(code: str, where: Callable[[int], str]) -> list[Step]:
    """The commands of a shell block: one per line, a line ending in `\\` or an open quote
    going on; comments dropped. Refuses what it cannot split (an unterminated quote)."""
    steps: list[Step] = []
    buf: list[str] = []
    quote: str | None = None
    line = start = 1
    i = 0

    def flush() -> None:
        text = "".join(buf).strip()
        if text:
            steps.append(Step(where(start), text))
        buf.clear()

    while i < len(code):
        c = code[i]
        if not "".join(buf).strip() and not c.isspace():
            start = line
        if quote == "'":
            quote = None if c == "'" else quote
            buf.append(c)
        elif quote == '"':
            if c == "\\" and i + 1 < len(code):
                buf.append(c)
                i += 1
                c = code[i]
            elif c == '"':
                quote = None
            buf.append(c)
        elif c == "\\" and code[i + 1:i + 2] == "\n":
            buf.append("\\\n")
            i += 1
            c = "\n"
        elif c in "'\"":
            quote = c
            buf.append(c)
        elif c == "#" and (not buf or buf[-1].isspace()):
            while i + 1 < len(code) and code[i + 1] != "\n":
                i += 1
        elif c == "\n":
            flush()
        else:
            buf.append(c)
        line += c == "\n"
        i += 1
    if quote is not None:
        raise AssertionError(f"{where(start)}: unterminated {quote} quote in the shell block")
    flush()
    return steps


def _blocks(path: Path, text: str, offset: int) -> list[Step]:
    rel = path.relative_to(ROOT).as_posix()
    steps: list[Step] = []
    for block in fenced_blocks(text):
        if block.lang not in SHELL_LANGS:
            continue
        if path == API_MD and not (("curl" in block.code and "$DETCAL" in block.code)
                                   or "export DETCAL=" in block.code):
            continue
        first = offset + block.line
        steps += split_commands(block.code, lambda n, first=first: f"{rel}:{first + n - 1}")
    return steps


def tour_steps() -> list[Step]:
    """The commands of README.md's tour section, then docs/api.md's curl examples."""
    text = README.read_text(encoding="utf-8")
    head, sep, rest = text.partition(f"\n{TOUR_HEADING}\n")
    assert sep, f"README.md has no '{TOUR_HEADING}' section"
    section = rest.split("\n## ", 1)[0]
    offset = head.count("\n") + 2                 # README line of the section's first line - 1
    readme = _blocks(README, section, offset)
    assert readme, f"README.md's '{TOUR_HEADING}' has no shell block"
    api = _blocks(API_MD, API_MD.read_text(encoding="utf-8"), 0)
    assert api, "docs/api.md has no curl example"
    return readme + api


# -- running -------------------------------------------------------------------------------------
def _substitute(step: Step, tour: Tour, used: set[str]) -> str:
    text = step.text
    for key, value in SUBSTITUTIONS.items():
        if key in text:
            used.add(key)
            text = text.replace(key, value(tour))
    left = re.findall(r"<[A-Za-z_]+>", text)
    assert not left, f"{step.where}: no substitution for {left} in {step.text!r}"
    return text


def _bash(tour: Tour, text: str, headers: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "DETCAL": tour.url, "TOKEN": tour.token,
           "DOCTOUR_HEADERS": str(headers)}
    return subprocess.run(["bash", "-c", PREAMBLE + text], cwd=tour.workdir, env=env,
                          capture_output=True, text=True, timeout=300, check=False)


def _last_response(headers: Path) -> tuple[int, str]:
    """Status and content type of the final response in a `--dump-header` file."""
    blocks = [b for b in re.split(r"\r?\n\r?\n", headers.read_text(errors="replace"))
              if b.startswith("HTTP/")]
    assert blocks, "curl wrote no response headers"
    lines = blocks[-1].splitlines()
    ctype = next((v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])
                  if k.strip().lower() == "content-type"), "")
    return int(lines[0].split()[1]), ctype


def run_step(step: Step, tour: Tour, used: set[str]) -> Any:
    """Run one step; its parsed JSON answer for a curl step, else None."""
    if step.kind == "skip":
        tour.ran.append(f"skipped {step.where} ({SKIPPED[step.words[0]]})")
        return None
    text = _substitute(step, tour, used)
    for name, make in INPUTS.items():
        if re.search(rf"@{re.escape(name)}\b", text) and not (tour.workdir / name).exists():
            make(tour.workdir)
    headers = tour.workdir / ".headers"
    headers.unlink(missing_ok=True)
    if step.kind == "export":
        names = [w.split("=", 1)[0] for w in step.words[1:] if "=" in w]
        assert names, f"{step.where}: an export that sets nothing: {step.text!r}"
        text += "\nprintf '%s\\n' " + " ".join(f'"${n}"' for n in names)
    proc = _bash(tour, text, headers)
    context = (f"{step.where}: `{text}` exited {proc.returncode}\nstdout: "
               f"{proc.stdout[-3000:]}\nstderr: {proc.stderr[-3000:]}")
    status, ctype = _last_response(headers) if headers.exists() else (None, "")
    if status is not None:
        context += f"\nHTTP {status} ({ctype})"
    assert proc.returncode == 0, context
    tour.ran.append(f"{step.where}: {text.splitlines()[0][:100]}")
    if step.kind == "export":
        expected = {"DETCAL": tour.url, "TOKEN": tour.token}
        got = dict(zip(names, proc.stdout.splitlines(), strict=True))
        for name, value in got.items():
            assert value == expected.get(name, value), f"{step.where}: {name}={value!r}"
        return None
    if step.kind != "curl":
        return None
    assert status is not None and status < 400, context
    out = step.output_file
    body = (tour.workdir / out).read_text() if out else proc.stdout
    route = step.route
    if route in NON_JSON:
        assert ctype.startswith(NON_JSON[route]), context
        return None
    assert ctype.startswith("application/json"), context
    try:
        return json.loads(body)
    except json.JSONDecodeError as exc:
        raise AssertionError(f"{context}\nnot JSON: {exc}") from exc


def watch_job(step: Step, tour: Tour, used: set[str], answer: dict,
              timeout_s: float = 120.0) -> dict:
    """Run a `GET /v1/jobs/{id}` step again until its job lands; it must succeed."""
    deadline = time.monotonic() + timeout_s
    while answer["state"] not in ("succeeded", "failed"):
        assert time.monotonic() < deadline, f"{step.where}: job still {answer['state']}"
        time.sleep(0.2)
        answer = run_step(step, tour, used)
    assert answer["state"] == "succeeded", f"{step.where}: {answer}"
    return answer
