"""Write a profile's graph to a file: ONNX (`torch.onnx.export`, dynamo) or TorchScript.

Both files run without detcal: the ONNX model with onnxruntime alone, the TorchScript module
with torch alone. The graph's description (`CalibrationGraph.metadata`, JSON: classes, levels,
inputs, outputs, conformal groups, the profile's sha256) travels with it: as the ONNX model's
metadata property `detcal`, and as the TorchScript archive's extra file `detcal.json`.
ONNX inputs have the declared `input_dtype` (float32 or float64) and dynamic N (0 allowed),
L and H; TorchScript takes any float dtype. Every output float is float64.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import json
import logging
import os
import warnings
from collections.abc import Iterator, Sequence
from typing import Any

import torch

from calibrators.core.defaults import DEFAULT_LEVELS
from calibrators.io import atomic_write
from calibrators.profile import CalibrationProfile
from detectors.export.graph import CalibrationGraph, ExportError, build_graph

#: The file formats `export_profile` writes.
EXPORT_FORMATS: tuple[str, ...] = ("onnx", "torchscript")
#: The ONNX input dtypes `export_profile` declares.
INPUT_DTYPES: dict[str, torch.dtype] = {"float64": torch.float64, "float32": torch.float32}
#: Key of the graph's description: ONNX metadata property, and `<key>.json` in TorchScript.
METADATA_KEY = "detcal"


def export_profile(profile: CalibrationProfile, path: str | os.PathLike[str],
                   format: str = "onnx", *, cov_source: str | None = None,
                   levels: Sequence[float] = DEFAULT_LEVELS, layer_logits: bool | None = None,
                   input_dtype: str = "float64", labels: bool = False) -> dict[str, Any]:
    """Write `profile`'s graph (`build_graph` with these options) to `path` atomically;
    returns its description (the metadata written with it). Raises `ExportError`."""
    if format not in EXPORT_FORMATS:
        raise ExportError(f"format must be one of {list(EXPORT_FORMATS)}, got {format!r}")
    if input_dtype not in INPUT_DTYPES:
        raise ExportError(f"input_dtype must be one of {list(INPUT_DTYPES)}, got "
                          f"{input_dtype!r}")
    graph = build_graph(profile, cov_source=cov_source, levels=levels,
                        layer_logits=layer_logits, labels=labels).eval()
    meta = json.loads(graph.metadata)
    meta["input_dtype"] = input_dtype if format == "onnx" else "any float"
    data = (_onnx_bytes(graph, INPUT_DTYPES[input_dtype], meta) if format == "onnx"
            else _torchscript_bytes(graph, meta))
    with atomic_write(path, "wb") as fh:
        fh.write(data)
    return meta


def example_inputs(graph: CalibrationGraph, dtype: torch.dtype = torch.float64,
                   n: int = 3, n_layers: int = 3, n_hypotheses: int = 3
                   ) -> tuple[torch.Tensor, ...]:
    """Inputs of the graph's shapes (N = `n`, L = `n_layers`, H = `n_hypotheses`) in its
    input order."""
    meta = json.loads(graph.metadata)
    width = len(meta["classes"]) + (1 if meta["score_mode"] == "softmax" else 0)
    dim = len(meta["cov_dims"])
    shapes = {"logits": (n, width), "layer_logits": (n, n_layers, width), "boxes": (n, 9),
              "layer_boxes": (n, n_layers, 9), "ego_xy": (n, 2),
              "hyp_boxes": (n, n_hypotheses, 9)}
    gen = torch.Generator().manual_seed(0)
    out = []
    for name in graph.input_names:
        if name == "covariances_raw":
            out.append(torch.eye(dim, dtype=dtype).expand(n, dim, dim).contiguous())
        elif name == "hyp_scores":   # group scores are >= 0
            out.append(torch.rand((n, n_hypotheses), generator=gen, dtype=dtype))
        elif name == "labels":       # class indices
            out.append(torch.randint(len(meta["classes"]), (n,), generator=gen))
        else:
            out.append(torch.randn(shapes[name], generator=gen, dtype=dtype))
    return tuple(out)


def _onnx_bytes(graph: CalibrationGraph, dtype: torch.dtype, meta: dict[str, Any]) -> bytes:
    """The ONNX model (dynamic N >= 0 and L) with the description as metadata."""
    try:
        import onnx
        import onnxscript  # noqa: F401 - torch.onnx.export(dynamo=True) needs it
    except ImportError as exc:
        raise ExportError(f"writing ONNX needs onnx and onnxscript (pip install "
                          f"'detcal[export]'): {exc}") from None

    args = example_inputs(graph, dtype)
    n = torch.export.Dim("N", min=0)
    layers = torch.export.Dim("L", min=2 if meta["modulation"] or meta["cov_source"] ==
                              "layers" else 1)
    hyps = torch.export.Dim("H", min=1)
    axes = {"logits": {0: n}, "layer_logits": {0: n, 1: layers}, "boxes": {0: n},
            "layer_boxes": {0: n, 1: layers}, "ego_xy": {0: n}, "covariances_raw": {0: n},
            "hyp_boxes": {0: n, 1: hyps}, "hyp_scores": {0: n, 1: hyps}, "labels": {0: n}}
    params = list(inspect.signature(graph.forward).parameters)   # forward's names
    dynamic = {param: axes[name] for param, name in zip(params, graph.input_names, strict=True)}
    with _quiet():
        # optimize=False: onnxscript's optimizer (0.7) drops the multiplication by the
        # constant 1 − 1e-6 of the knot calibrators (an error of 1e-6 in their scores).
        program = torch.onnx.export(graph, args, dynamo=True, input_names=graph.input_names,
                                    output_names=graph.output_names, dynamic_shapes=dynamic,
                                    optimize=False, verbose=False)
    if program is None:
        raise ExportError("torch.onnx.export returned no program")
    model = program.model_proto
    onnx.helper.set_model_props(model, {METADATA_KEY: json.dumps(meta, allow_nan=False)})
    return model.SerializeToString()


def _torchscript_bytes(graph: CalibrationGraph, meta: dict[str, Any]) -> bytes:
    """The scripted module with the description as the extra file `detcal.json`."""
    buf = io.BytesIO()
    with _quiet():
        torch.jit.save(torch.jit.script(graph), buf,
                       _extra_files={f"{METADATA_KEY}.json": json.dumps(meta, allow_nan=False)})
    return buf.getvalue()


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Silence the exporters' progress lines and their deprecation and logging chatter."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            yield
    finally:
        logger.setLevel(level)
