"""The code in README.md and docs/*.md runs, against the shipped validation dump.

Every fenced ```python block of README.md and docs/*.md (not docs/report/, which is generated)
runs as a test: the blocks of one file in order, in one shared namespace (a later block may use
names an earlier one defined), in a fresh working directory that holds the input files the
blocks name (`val.npz` is a copy of the shipped `detectors/data/lidar_val.npz`; see `INPUTS`).
A new doc with a python block is picked up without touching this file. A traceback points at
the markdown file and line of the failing statement.

The README's "CLI" section runs through the installed `detcal` in such a directory too. The
curl tours need a live server; tests/e2e covers the service.
"""

from __future__ import annotations

import linecache
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

import detectors

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]  # not recursive: docs/report/ is generated
SHIPPED_DUMP = Path(detectors.__file__).parent / "data" / "lidar_val.npz"
DETCAL = Path(sys.executable).parent / "detcal"

_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^`\s]*)[^`]*$")


@dataclass(frozen=True)
class Block:
    """One fenced code block: its language, first code line (1-based) and dedented code."""

    lang: str
    line: int
    code: str


def fenced_blocks(text: str) -> list[Block]:
    """Every fenced code block of the markdown `text`, in order (lines counted from its start)."""
    blocks: list[Block] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        opening = _FENCE.match(lines[i])
        if not opening:
            i += 1
            continue
        indent, fence = opening["indent"], opening["fence"]
        body: list[str] = []
        j = i + 1
        while j < len(lines):
            closing = _FENCE.match(lines[j])
            if (closing and closing["fence"][0] == fence[0]
                    and len(closing["fence"]) >= len(fence) and not closing["info"]):
                break
            body.append(lines[j][len(indent):] if lines[j].startswith(indent) else lines[j])
            j += 1
        blocks.append(Block(opening["info"].lower(), i + 2, "\n".join(body) + "\n"))
        i = j + 1
    return blocks


#: A python block that reads this needs a live server: tests/e2e/test_docs_tour.py runs it.
SERVER_MARK = 'os.environ["DETCAL"]'


def python_blocks(path: Path, server: bool = False) -> list[Block]:
    """The ```python blocks of the markdown file `path`: those that run on their own, or with
    `server` those that call a live server (`SERVER_MARK`)."""
    text = path.read_text(encoding="utf-8")
    return [b for b in fenced_blocks(text) if b.lang in ("python", "py", "python3")
            and (SERVER_MARK in b.code) == server]


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


DOCS_WITH_PYTHON = [p for p in DOCS if python_blocks(p)]


# -- inputs the examples name ------------------------------------------------------------------
def _val_npz(path: Path) -> None:
    shutil.copyfile(SHIPPED_DUMP, path)


def _profile_json(path: Path) -> None:
    """A profile fit on the shipped dump with the library's defaults."""
    from calibrators import fit_profile, load_dump

    path.write_text(fit_profile(load_dump(SHIPPED_DUMP)).to_json())


def _results_json(path: Path) -> None:
    """The shipped dump as a nuScenes results JSON (detections only, with their covariance)."""
    from calibrators import load_dump, save_nuscenes

    save_nuscenes(load_dump(SHIPPED_DUMP), path)


INPUTS: dict[str, Callable[[Path], None]] = {
    "val.npz": _val_npz,
    "profile.json": _profile_json,
    "results.json": _results_json,
    "results_nusc.json": _results_json,
}


@pytest.fixture(scope="session")
def inputs(tmp_path_factory) -> Callable[[Path, str], None]:
    """`put(workdir, text)`: copy into `workdir` every input file that `text` names (each is
    built once per session)."""
    store = tmp_path_factory.mktemp("doc_inputs")

    def put(workdir: Path, text: str) -> None:
        for name, build in INPUTS.items():
            if name not in text:
                continue
            source = store / name
            if not source.exists():
                build(source)
            shutil.copyfile(source, workdir / name)

    return put


# -- the tests ---------------------------------------------------------------------------------
def test_readme_has_python_examples():
    """The harness cannot silently test nothing: the README's library example is a python
    block, and so is at least one docs page's."""
    assert python_blocks(README), "README.md has no ```python block"
    assert README in DOCS_WITH_PYTHON and len(DOCS_WITH_PYTHON) >= 2


@pytest.mark.parametrize("doc", DOCS_WITH_PYTHON, ids=_rel)
def test_python_examples_run(doc: Path, tmp_path: Path, monkeypatch, inputs):
    blocks = python_blocks(doc)
    inputs(tmp_path, "".join(b.code for b in blocks))
    monkeypatch.chdir(tmp_path)
    _register_source(doc, blocks)
    namespace: dict[str, object] = {"__name__": "__main__"}
    for block in blocks:
        source = "\n" * (block.line - 1) + block.code  # line numbers are the markdown's
        exec(compile(source, str(doc), "exec"), namespace)


def _register_source(doc: Path, blocks: list[Block]) -> None:
    """Let tracebacks quote the failing statement: `linecache` gets, for `doc`, its python
    blocks at their own lines and blank lines elsewhere (parseable, unlike the markdown)."""
    lines = [""] * len(doc.read_text(encoding="utf-8").splitlines())
    for block in blocks:
        code = block.code.splitlines()
        lines[block.line - 1:block.line - 1 + len(code)] = code
    text = [line + "\n" for line in lines]
    linecache.cache[str(doc)] = (sum(map(len, text)), None, text, str(doc))


def cli_commands(path: Path = README, section_title: str | None = "CLI") -> list[list[str]]:
    """The `detcal ...` command lines of the shell blocks in the "## CLI" section of `path`
    (`section_title` None: of the whole file)."""
    section = path.read_text(encoding="utf-8")
    if section_title is not None:
        parts = section.split(f"\n## {section_title}\n", 1)
        assert len(parts) == 2, f"{_rel(path)} has no '## {section_title}' section"
        section = parts[1].split("\n## ", 1)[0]
    commands = []
    for block in fenced_blocks(section):
        if block.lang not in ("sh", "bash", "shell", "console"):
            continue
        for line in block.code.replace("\\\n", " ").splitlines():  # join continued lines
            if not line.lstrip().startswith("detcal "):
                continue
            words = shlex.split(line, comments=True)
            if words and words[0] == "detcal":
                commands.append(words)
    return commands


def test_readme_cli_section_runs(tmp_path: Path, inputs):
    commands = cli_commands()
    assert [c[1] for c in commands][:2] == ["fit", "evaluate"], commands
    inputs(tmp_path, " ".join(" ".join(c) for c in commands))
    for command in commands:
        result = subprocess.run([str(DETCAL), *command[1:]], cwd=tmp_path, capture_output=True,
                                text=True, timeout=300, check=False)
        assert result.returncode == 0, (f"{shlex.join(command)} exited {result.returncode}:\n"
                                        f"{result.stdout[-2000:]}\n{result.stderr[-2000:]}")


def test_api_doc_detcal_calibrate_commands_run(tmp_path: Path, inputs):
    """docs/api.md's `detcal calibrate` examples write the documented keys."""
    import json

    commands = [c for c in cli_commands(ROOT / "docs" / "api.md", None) if c[1] == "calibrate"]
    assert len(commands) >= 2, commands
    inputs(tmp_path, " ".join(" ".join(c) for c in commands))
    for command in commands:
        result = subprocess.run([str(DETCAL), *command[1:]], cwd=tmp_path, capture_output=True,
                                text=True, timeout=300, check=False)
        assert result.returncode == 0, (shlex.join(command), result.stderr[-2000:])
        doc = json.loads((tmp_path / command[command.index("--out") + 1]).read_text())
        box = next(iter(doc["results"].values()))[0]
        assert {"detection_score", "detection_score_raw", "covariance", "ellipses"} <= set(box)
