"""A calibration profile exported as a graph the detector can run: ONNX or TorchScript.

`build_graph(profile, ...)` assembles the profile's stages as one torch module
(`detectors.export.graph`); `export_profile(profile, path, format=...)` writes it
(`detectors.export.writers`). docs/export.md documents the graph's inputs and outputs.
"""

from detectors.export.graph import CalibrationGraph, ExportError, build_graph
from detectors.export.writers import EXPORT_FORMATS, export_profile

__all__ = ["EXPORT_FORMATS", "CalibrationGraph", "ExportError", "build_graph", "export_profile"]
