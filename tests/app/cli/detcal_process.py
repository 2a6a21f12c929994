"""The installed `detcal` entry point run as a subprocess: the CLI tests' end-to-end runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

DETCAL = Path(sys.executable).parent / "detcal"


def detcal(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([str(DETCAL), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, check=False)
