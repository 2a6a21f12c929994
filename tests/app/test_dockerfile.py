"""The Dockerfile cannot be built here (no Docker engine): parse it and check what it relies on."""

from __future__ import annotations

import json
import re
import shlex
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _instructions() -> list[tuple[str, str]]:
    text = (ROOT / "Dockerfile").read_text()
    text = re.sub(r"\\\n", " ", text)
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def test_base_image_user_volume_and_healthcheck():
    ins = _instructions()
    ops = [op for op, _ in ins]
    assert ins[0] == ("FROM", "python:3.11-slim")
    user = [rest for op, rest in ins if op == "USER"]
    assert user and user[-1] not in ("root", "0")
    assert ops.index("USER") > max(i for i, op in enumerate(ops) if op == "RUN")
    assert ("VOLUME", "/data") in ins
    health = next(rest for op, rest in ins if op == "HEALTHCHECK")
    assert "/healthz" in health and "urllib" in health
    assert ("EXPOSE", "8000") in ins


def test_copied_paths_exist():
    for op, rest in _instructions():
        if op == "COPY":
            *sources, _dest = shlex.split(rest)
            for src in sources:
                assert (ROOT / src).exists(), f"Dockerfile copies {src}, which is missing"


def test_install_uses_constraints_and_existing_extras():
    run = " ".join(rest for op, rest in _instructions() if op == "RUN")
    assert "-c constraints.txt" in run
    extras = re.search(r'"\.\[([a-z,]+)\]"', run)
    assert extras
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for extra in extras.group(1).split(","):
        assert extra in project["optional-dependencies"], extra
    assert "torch" in (ROOT / "constraints.txt").read_text()
    assert "download.pytorch.org/whl/cpu" in run          # CPU-only torch wheel


def test_cmd_is_detcal_serve_with_existing_options():
    cmd = json.loads(next(rest for op, rest in _instructions() if op == "CMD"))
    assert cmd[:2] == ["detcal", "serve"]
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["detcal"] == "app.cli:main"
    from app.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(cmd[1:])
    assert args.command == "serve" and args.host == "0.0.0.0"
    env = dict(re.findall(r"(DETCAL_[A-Z_]+)=(\S+)", " ".join(
        rest for op, rest in _instructions() if op == "ENV")))
    from app.settings import Settings

    for key in env:
        assert key.removeprefix("DETCAL_").lower() in Settings.model_fields, key
