"""Write one benchmark's section of docs/benchmarks.md, leaving the other sections alone."""

from __future__ import annotations

import platform
import re
from datetime import UTC, datetime
from pathlib import Path

DOC = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
HEADER = (
    "# Benchmarks\n\n"
    "Every figure here is printed by a script in `bench/`, which rewrites its own section.\n"
    "Ratios compare against a reference measured in the same run on the same machine.\n"
)


def machine() -> str:
    """One line describing where the figures were measured."""
    import os

    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, " \
           f"Python {platform.python_version()}"


def write_section(name: str, markdown: str, doc: Path = DOC, header: str = HEADER) -> None:
    """Replace (or append) the section `name` of `doc` (docs/benchmarks.md; a new file starts
    with `header`) with `markdown`."""
    text = doc.read_text() if doc.exists() else header
    stamp = datetime.now(UTC).strftime("%Y-%m-%d")
    body = f"<!-- bench:{name} -->\n{markdown.rstrip()}\n\n_Measured {stamp} on {machine()}._\n" \
           f"<!-- /bench:{name} -->"
    pattern = re.compile(rf"<!-- bench:{re.escape(name)} -->.*?<!-- /bench:{re.escape(name)} -->",
                         re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _: body, text)
    else:
        text = text.rstrip() + "\n\n" + body + "\n"
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text(text)


def report(name: str, markdown: str) -> int:
    """Print a benchmark's `markdown` and write it as section `name`; the exit status 0."""
    print(markdown)
    write_section(name, markdown)
    return 0
