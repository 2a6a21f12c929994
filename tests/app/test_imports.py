"""Importing the service loads neither torch, the simulator nor matplotlib (they load when a
request first needs them: /v1/detect, the dashboard's plots and bird's-eye view)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "matplotlib", "detectors.sim")

_PROBE = """
import json, sys
import app.main
heavy = {heavy!r}
print(json.dumps(sorted(m for m in sys.modules
                        if any(m == h or m.startswith(h + ".") for h in heavy))))
"""


def _heavy_modules_after(statement: str) -> list[str]:
    """The heavy modules loaded by a fresh interpreter after `statement` and `import app.main`."""
    code = statement + "\n" + _PROBE.format(heavy=HEAVY)
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_import_app_main_loads_no_torch_simulator_or_matplotlib():
    assert _heavy_modules_after("") == []


def test_the_probe_sees_a_heavy_module_when_one_is_loaded():
    """The check can fail: a heavy module imported first is reported."""
    assert "matplotlib" in _heavy_modules_after("import matplotlib")
