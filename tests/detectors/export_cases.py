"""Profiles, dumps and comparisons shared by the export tests (`test_export*.py`).

Dumps: the shipped lidar validation dump, small dumps of the shipped radar1, radar5 and camera
detectors (a few frames each), and synthetic ones. `CASES` fit profiles of every score,
covariance and region method, both score modes, modulation, every covariance source and a
version-1 profile; `library` runs the library's serving path and `graph_inputs` gives the
same arrays in a graph's input order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import detectors
from calibrators import CalibrationProfile, fit_profile, load_dump
from calibrators.data import Dump, synthetic_dump
from calibrators.profile import CalibratedDetections

SHIPPED_DUMP = Path(detectors.__file__).parent / "data" / "lidar_val.npz"
V1_PROFILE = (Path(__file__).parents[1] / "calibrators" / "profile" / "data"
              / "profile_v1.json")
LEVELS = (0.5, 0.9, 0.95)
#: Frames of the shipped detectors' dumps (radar1 takes ~0.6 s a frame).
DETECTOR_FRAMES = 4
#: The contract is 1e-6; measured differences are below 1e-11 (float64 throughout), so a
#: tighter bound catches a constant rounded or dropped on the way (as onnxscript's optimizer
#: dropped a factor 1 − 1e-6, a 1e-6 error that a 1e-6 bound let through).
TOLERANCE = 1e-9


@dataclass(frozen=True)
class Case:
    """One profile to export: the dump it is fit on (and served), fit options (None: read
    `profile_file`), the covariance source served, whether to write ONNX too (slower), and
    the declared input dtype; `layer_logits` True takes every layer's logits without
    modulation."""

    id: str
    dump: str
    options: dict[str, Any] | None
    source: str | None = None
    onnx: bool = False
    dtype: str = "float64"
    profile_file: Path | None = field(default=None)
    layer_logits: bool | None = None


THESIS = {"score_method": "temperature", "cov_method": "depth", "region_method": "gaussian"}
CASES = [
    Case("lidar-auto-given", "lidar", {}, "given", onnx=True),
    Case("lidar-auto-layers", "lidar", {}, "layers"),
    Case("lidar-auto-none", "lidar", {}, "none"),
    Case("v1-thesis-sigmoid", "sigmoid", {**THESIS, "cov_source": "given",
                                          "other_sources": False}, onnx=True),
    Case("v1-file", "sigmoid", None, profile_file=V1_PROFILE),
    Case("softmax-temperature", "softmax", {**THESIS, "cov_source": "given"}),
    Case("softmax-temperature-layer-logits", "softmax", {**THESIS, "cov_source": "given"},
         layer_logits=True),
    Case("softmax-modulation-class-temperature", "softmax",
         {"modulation": True, "score_method": "class_temperature", "cov_method": "depth",
          "region_method": "conformal", "cov_source": "none", "min_group": 20}, onnx=True),
    Case("radar1-isotonic-conformal-layers", "radar1",
         {"score_method": "isotonic", "cov_method": "depth", "region_method": "conformal",
          "cov_source": "layers", "min_group": 20}, onnx=True),
    Case("radar5-histogram-shrinkage", "radar5",
         {"score_method": "histogram", "cov_method": "shrinkage", "region_method": "gaussian",
          "cov_source": "given"}, onnx=True),
    Case("camera-platt-range-float32", "camera",
         {"score_method": "platt_range", "cov_method": "depth", "region_method": "conformal",
          "cov_source": "given", "min_group": 20}, onnx=True, dtype="float32"),
    Case("yaw-layers-float32", "sigmoid",
         {**THESIS, "dims": ("x", "y", "yaw"), "cov_source": "layers"}, onnx=True,
         dtype="float32"),
    Case("xz-dims-no-regions", "sigmoid", {**THESIS, "dims": ("x", "z"),
                                           "cov_source": "layers"}),
    Case("hypotheses-conformal", "hypotheses",
         {"cov_source": "hypotheses", "region_method": "conformal", "min_group": 20},
         onnx=True),
    Case("hypotheses-served-beside-given", "hypotheses", {}, "hypotheses"),
    Case("yaw-hypotheses-shrinkage-float32", "hypotheses",
         {**THESIS, "cov_method": "shrinkage", "dims": ("x", "y", "yaw"),
          "cov_source": "hypotheses"}, onnx=True, dtype="float32"),
]


def build_dumps() -> dict[str, Dump]:
    """Every dump the cases name."""
    from detectors.dumpwriter import build_dump
    from detectors.registry import build_detector
    from detectors.sim import SPLITS

    seeds = list(SPLITS["val"])[:DETECTOR_FRAMES]
    dumps = {"lidar": load_dump(SHIPPED_DUMP),
             "sigmoid": synthetic_dump(n_frames=40, seed=11),
             "softmax": synthetic_dump(n_frames=40, score_mode="softmax", temperature=1.5,
                                       seed=12),
             "hypotheses": synthetic_dump(n_frames=40, seed=13, n_hypotheses=4)}
    for sensor in ("radar1", "radar5", "camera"):
        dumps[sensor] = build_dump(build_detector(sensor), seeds)
    return dumps


def case_profile(case: Case, dump: Dump) -> CalibrationProfile:
    if case.options is None:
        assert case.profile_file is not None
        return CalibrationProfile.from_json(case.profile_file.read_text())
    return fit_profile(dump, **case.options)


def _as(array: np.ndarray | None, dtype: str) -> np.ndarray | None:
    return None if array is None else np.ascontiguousarray(array, dtype=dtype)


def arrays(dump: Dump, dtype: str) -> dict[str, np.ndarray]:
    """The dump's arrays under every graph input name, in `dtype`."""
    return {"logits": _as(dump.det_logits[:, -1], dtype),
            "layer_logits": _as(dump.det_logits, dtype),
            "boxes": _as(dump.final_boxes, dtype), "layer_boxes": _as(dump.det_boxes, dtype),
            "ego_xy": _as(dump.ego_xy(dump.det_frame), dtype),
            "covariances_raw": _as(dump.det_cov, dtype),
            "hyp_boxes": _as(dump.det_hyp_boxes, dtype),
            "hyp_scores": _as(dump.det_hyp_scores, dtype)}


def graph_inputs(names: list[str], values: dict[str, np.ndarray]) -> list[np.ndarray]:
    return [values[name] for name in names]


def library(profile: CalibrationProfile, values: dict[str, np.ndarray], source: str,
            layer_logits: bool) -> CalibratedDetections:
    """The library's serving path on the same arrays."""
    return profile.calibrate(
        logits=None if layer_logits else values["logits"],
        layer_logits=values["layer_logits"] if layer_logits else None,
        boxes=values["boxes"], ego_xy=values["ego_xy"],
        covariances=values["covariances_raw"] if source == "given" else None,
        layer_boxes=values["layer_boxes"] if source == "layers" else None,
        hyp_boxes=values["hyp_boxes"] if source == "hypotheses" else None,
        hyp_scores=values["hyp_scores"] if source == "hypotheses" else None, levels=LEVELS)


def differences(out: dict[str, np.ndarray], lib: CalibratedDetections
                ) -> dict[str, tuple[float, float]]:
    """`{output: (max abs difference, max relative difference)}` of the graph's outputs
    against the library's; integer outputs must be equal (checked here)."""
    assert np.array_equal(out["labels"], lib.labels)
    pairs = {"scores": lib.scores, "scores_raw": lib.scores_raw, "distances": lib.distances,
             "covariances": lib.covariances}
    if lib.class_scores is not None:
        pairs["class_scores"] = lib.class_scores
    if lib.regions:
        qs = list(lib.regions)
        pairs["radii"] = np.stack([lib.region_radii[q] for q in qs], axis=1)
        pairs["semi_major"] = np.stack([lib.regions[q].semi_major for q in qs], axis=1)
        pairs["semi_minor"] = np.stack([lib.regions[q].semi_minor for q in qs], axis=1)
    assert set(out) - {"labels", "region_group", "angle"} == set(pairs), sorted(out)
    result = {}
    for name, want in pairs.items():
        result[name] = _diff(np.asarray(out[name]), np.asarray(want))
    if lib.regions:
        angle = np.asarray(lib.regions[LEVELS[0]].angle)
        # The same axis: an angle at -pi/2 + tiny and one at pi/2 are one ellipse.
        turn = np.abs((np.asarray(out["angle"]) - angle + math.pi / 2) % math.pi - math.pi / 2)
        result["angle"] = (float(turn.max(initial=0.0)),
                           float((turn / np.maximum(np.abs(angle), 1e-300)).max(initial=0.0)))
    if lib.region_groups is not None:
        _same_partition(np.asarray(out["region_group"]), lib.region_groups)
    return result


def _diff(got: np.ndarray, want: np.ndarray) -> tuple[float, float]:
    assert got.shape == want.shape, (got.shape, want.shape)
    gap = np.abs(got - want)
    rel = gap / np.maximum(np.abs(want), 1e-300)
    return float(gap.max(initial=0.0)), float(rel.max(initial=0.0))


def _same_partition(group: np.ndarray, names: list[str]) -> None:
    """The graph's group indices and the library's group names split the detections alike."""
    pairs = set(zip(group.tolist(), names, strict=True))
    assert len(pairs) == len({g for g, _ in pairs}) == len({n for _, n in pairs}), pairs
