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


def test_install_uses_the_lock_and_existing_extras():
    run = " ".join(rest for op, rest in _instructions() if op == "RUN")
    assert "-c requirements.lock" in run
    extras = re.search(r'"\.\[([a-z,]+)\]"', run)
    assert extras
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for extra in extras.group(1).split(","):
        assert extra in project["optional-dependencies"], extra
    assert "torch==2.13.0\n" in (ROOT / "requirements.lock").read_text()
    assert "download.pytorch.org/whl/cpu" in run          # CPU-only torch wheel


def _requirement_name(spec: str) -> str:
    return re.split(r"[<>=!~;\[ ]", spec, maxsplit=1)[0].strip().lower().replace("_", "-")


def test_the_lock_pins_every_declared_dependency_exactly():
    """Every runtime and test dependency of every extra has one `==` pin in the lock, and the
    Makefile installs from it (what `.ci/run` calls)."""
    lines = [ln for ln in (ROOT / "requirements.lock").read_text().splitlines()
             if ln and not ln.startswith("#")]
    pins = {}
    for line in lines:
        name, sep, version = line.partition("==")
        assert sep and version and " " not in version, f"not an exact pin: {line!r}"
        pins[_requirement_name(name)] = version
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        declared += [d for d in extra if not d.startswith("detcal[")]
    missing = sorted({_requirement_name(d) for d in declared} - set(pins))
    assert not missing, f"declared but not locked: {missing}"
    makefile = (ROOT / "Makefile").read_text()
    assert "-c $(LOCK)" in makefile and "LOCK := requirements.lock" in makefile
    assert "make test" in (ROOT / ".ci" / "run").read_text()


def test_cmd_is_detcal_serve_with_existing_options():
    cmd = json.loads(next(rest for op, rest in _instructions() if op == "CMD"))
    assert cmd[:2] == ["detcal", "serve"]
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["detcal"] == "app.cli.main:main"
    from app.cli.main import build_parser

    parser = build_parser()
    args = parser.parse_args(cmd[1:])
    assert args.command == "serve" and args.host == "0.0.0.0"
    env = dict(re.findall(r"(DETCAL_[A-Z_]+)=(\S+)", " ".join(
        rest for op, rest in _instructions() if op == "ENV")))
    from app.settings import Settings

    for key in env:
        assert key.removeprefix("DETCAL_").lower() in Settings.model_fields, key
