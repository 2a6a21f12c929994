"""The library's vocabulary, defined once: box fields, covariance sources, score modes,
and angle wrapping (JSON-safe values: `calibrators.core.json_safe`; the installed version:
`calibrators.core.version`).

Every other module (and `detectors/`, `app/`) imports these names instead of spelling them
again.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: The 9 fields of a box row `[.., 9]`, in column order (nuScenes convention, z = centre).
BOX_FIELDS: tuple[str, ...] = ("x", "y", "z", "w", "l", "h", "yaw", "vx", "vy")
#: Column of each box field.
BOX_INDEX: dict[str, int] = {name: i for i, name in enumerate(BOX_FIELDS)}
#: Where a profile's raw covariance Σ comes from: the detection's own `covariance` (`given`),
#: the spread of its box across decoder layers (`layers`), or nowhere (`none`, Σ = 0), or the
#: group-score-weighted spread of its H box hypotheses (`hypotheses`, group regression heads).
COV_SOURCES: tuple[str, ...] = ("given", "layers", "none", "hypotheses")
#: What a fit accepts for `cov_source`: a source, or `auto` (resolved from the dump).
COV_SOURCE_CHOICES: tuple[str, ...] = ("auto", *COV_SOURCES)
#: `sigmoid`: C independent class logits; `softmax`: C + 1 columns, the last is no-object.
SCORE_MODES: tuple[str, ...] = ("sigmoid", "softmax")
#: Score calibration of a profile: one global temperature (the thesis), or a per-class
#: calibrator of the label's logit (`calibrators.scores`).
SCORE_METHODS: tuple[str, ...] = ("temperature", "class_temperature", "platt", "platt_range",
                                  "isotonic", "histogram")
#: Covariance scaling: `Σ + k_c·d·I` (depth, the thesis) or `s_c·Σ + k_c·d·I` (shrinkage).
COV_METHODS: tuple[str, ...] = ("depth", "shrinkage")
#: Uncertainty regions: χ²₂ radii of a Gaussian, or split-conformal radii per class × range.
REGION_METHODS: tuple[str, ...] = ("gaussian", "conformal")
#: What the conformal radii are calibrated on: the calibration part's true positives under
#: the Σ' fit on the training part (`split`), or every fit true positive, each part scored
#: under the Σ' fit on the other (`cross`, served with the Σ' fit on the whole fit part).
REGION_CALIBRATIONS: tuple[str, ...] = ("split", "cross")
#: What a stored profile calibrates: `3d` boxes (a `CalibrationProfile`, whose JSON has no
#: `kind` key) or image-plane `boxes2d` (a `calibrators.boxes2d.Profile2D`, `"kind": "boxes2d"`).
PROFILE_KINDS: tuple[str, ...] = ("3d", "boxes2d")


def profile_kind(document: object) -> str:
    """The `PROFILE_KINDS` entry of a decoded profile JSON document: its `kind` key, `3d`
    when it has none (every profile written before 2-D profiles existed). ValueError for a
    `kind` that is not one of them."""
    if not isinstance(document, dict) or "kind" not in document:
        return "3d"
    kind = document["kind"]
    if kind not in PROFILE_KINDS[1:]:
        raise ValueError(f"profile kind must be one of {list(PROFILE_KINDS[1:])} (or absent "
                         f"for a 3-D profile), got {kind!r}")
    return str(kind)


def check_dims(dims: str | Sequence[str]) -> tuple[str, ...]:
    """Regression dims as a tuple of distinct box fields; `"x,y"` is accepted for `("x", "y")`.

    Raises ValueError naming `dims` for an empty, unknown or repeated field.
    """
    if isinstance(dims, str):
        dims = [d.strip() for d in dims.split(",") if d.strip()]
    try:
        out = tuple(str(d) for d in dims)
    except TypeError:
        raise ValueError(f"dims must be a list of box fields, got {type(dims).__name__}") from None
    if not out:
        raise ValueError("dims must name at least one box field")
    for d in out:
        if d not in BOX_INDEX:
            raise ValueError(f"dims has unknown box field {d!r}; known: {list(BOX_FIELDS)}")
    if len(set(out)) != len(out):
        raise ValueError(f"dims has duplicate names: {list(out)}")
    return out


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Angles (rad) wrapped to (-pi, pi], elementwise."""
    return np.pi - np.mod(np.pi - np.asarray(angle, dtype=np.float64), 2.0 * np.pi)




