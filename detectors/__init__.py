"""Bundled CPU detectors: simulated world (`detectors.sim`), DETR-style models, weights.

`from detectors import build_detector` is the public entry point (detectors.registry). It is
resolved lazily so that `import detectors.sim` or the `detcal` CLI do not pay torch's import
time until a model is actually needed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from detectors.registry import build_detector

__all__ = ["build_detector"]


def __getattr__(name: str) -> Any:
    if name == "build_detector":
        from detectors.registry import build_detector

        return build_detector
    raise AttributeError(f"module 'detectors' has no attribute {name!r}")
