"""How far each edge of a detected box is likely to be off: a log-linear model of the edge
error's scale, fit on true positives kept apart from the calibration ones, that the
`adaptive` box regions divide the error by (normalised split-conformal: Lei et al. 2018,
"Distribution-free predictive inference for regression", §5.2; Papadopoulos et al. 2008).

Per detection and edge j (x1, y1, x2, y2), with `e_j` the true edge minus the detected one:

    log(|e_j| + ε_e) ≈ φ_j · β          scale_j = exp(φ_j · β)                    (1)

fit by least squares over every (detection, edge) of the fitting true positives, where

- `edge`: one intercept per edge (x edges and y edges differ: images are wider than tall);
- `log_along`, `log_across`: the log of the detected box's extent along the edge's axis (the
  width for x1, x2) and across it (errors grow with the box);
- `score_logit`: the logit of the detector's raw score (unsure detections are off more);
- `log_layer_sigma` (when the detections carry decoder-layer boxes): `log(σ_j + ε_σ)` with
  `σ_j` the edge's standard deviation across the layers (`edge_covariance` without a floor);
  the layers disagree where the box is hard;
- `at_border` (when the image size is known): the detected edge lies within `BORDER_PX` of its
  image's border: a truncated object's box is clipped there and that edge is right.

The floors `ε_e` and `ε_σ` are a fraction (`FLOOR_FRACTION`) of the fitting errors' and
σ's medians, so the model reads the same in any pixel unit. Any fixed function of the
detection keeps split-conformal coverage exact (the calibration scores `max_j |e_j| /
scale_j` are exchangeable with the test one); a better model only makes the regions tighter
where detections are easy and wider where they are hard.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibrators.boxes2d._boxes import check_bbox
from calibrators.boxes2d._edges import box_edges
from calibrators.core.checks import as_float_array, check_fitted, check_length
from calibrators.core.errors import FieldError

__all__ = ["BORDER_PX", "FLOOR_FRACTION", "EdgeErrorScale"]

#: An edge within this many pixels of its image's border counts as at the border.
BORDER_PX: float = 1.5
#: The floors ε_e and ε_σ of (1), as a fraction of the fitting data's medians.
FLOOR_FRACTION: float = 0.2
_TINY = 1e-9


class EdgeErrorScale:
    """The log-linear edge-error scale of the module docstring (1).

    Fitted: `features_` (the terms of φ, in `coef_`'s order), `coef_ [F]`, `error_floor_`
    (ε_e, pixels), `sigma_floor_` (ε_σ, pixels; None without layer σ), `n_` (fitting boxes).
    """

    def fit(self, boxes: np.ndarray, true_boxes: np.ndarray, score: np.ndarray,
            layer_sigma: np.ndarray | None = None, image_size: np.ndarray | None = None
            ) -> EdgeErrorScale:
        """Fit on matched true positives: detected `boxes [M, 4]` and their `true_boxes
        [M, 4]` (COCO x, y, w, h), the detector's raw `score [M]` in [0, 1], each edge's σ
        across the decoder layers `layer_sigma [M, 4]` (optional) and each box's image
        `image_size [M, 2]` (width, height; optional). Returns self."""
        det = check_bbox("boxes", boxes, None)
        true = check_bbox("true_boxes", true_boxes, len(det), "boxes")
        if len(det) < 2:
            raise ValueError("the edge-error scale needs at least 2 true positives")
        err = np.abs(box_edges(true) - box_edges(det))
        self.error_floor_ = max(FLOOR_FRACTION * float(np.median(err)), _TINY)
        self.sigma_floor_ = None
        if layer_sigma is not None:
            sig = _sigma(layer_sigma, len(det))
            self.sigma_floor_ = max(FLOOR_FRACTION * float(np.median(sig)), _TINY)
        self.features_ = _terms(layer_sigma is not None, image_size is not None)
        x = self._design(det, score, layer_sigma, image_size)          # [M, 4, F]
        y = np.log(err + self.error_floor_)                            # [M, 4]
        self.coef_, *_ = np.linalg.lstsq(x.reshape(-1, x.shape[2]), y.reshape(-1),
                                         rcond=None)
        self.n_ = len(det)
        return self

    def predict(self, boxes: np.ndarray, score: np.ndarray,
                layer_sigma: np.ndarray | None = None,
                image_size: np.ndarray | None = None) -> np.ndarray:
        """`[N, 4]` scale (pixels, > 0) of each edge's error for detected `boxes [N, 4]`
        with `score [N]`, and `layer_sigma [N, 4]` / `image_size [N, 2]` where the model
        was fit with them (a FieldError names the one missing)."""
        check_fitted(self, "coef_")
        det = check_bbox("boxes", boxes, None)
        if len(det) == 0:
            return np.zeros((0, 4))
        return np.exp(self._design(det, score, layer_sigma, image_size) @ self.coef_)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict; `from_dict` predicts identically."""
        check_fitted(self, "coef_")
        return {"features": list(self.features_), "coef": [float(c) for c in self.coef_],
                "error_floor": self.error_floor_, "sigma_floor": self.sigma_floor_,
                "n": int(self.n_)}

    @classmethod
    def from_dict(cls, data: Any) -> EdgeErrorScale:
        """The fitted model `to_dict` wrote; ValueError naming a missing or bad key."""
        if not isinstance(data, dict) or set(data) != {"features", "coef", "error_floor",
                                                       "sigma_floor", "n"}:
            raise ValueError("scale must be an object with features, coef, error_floor, "
                             "sigma_floor and n")
        features = data["features"]
        if not isinstance(features, list) or not features or any(
                f not in _ALL_TERMS for f in features):
            raise ValueError(f"scale.features must list terms of {list(_ALL_TERMS)}")
        layered = "log_layer_sigma" in features
        if features != _terms(layered, "at_border" in features):
            raise ValueError("scale.features are not a term list this detcal writes")
        coef = np.asarray(data["coef"], dtype=np.float64) if isinstance(data["coef"], list) \
            else None
        if coef is None or coef.shape != (_width(features),) or not np.isfinite(coef).all():
            raise ValueError(f"scale.coef must be {_width(features)} finite numbers")
        self = cls()
        self.features_ = features
        self.coef_ = coef
        self.error_floor_ = _positive("error_floor", data["error_floor"])
        self.sigma_floor_ = _positive("sigma_floor", data["sigma_floor"]) if layered else None
        if not layered and data["sigma_floor"] is not None:
            raise ValueError("scale.sigma_floor must be null without log_layer_sigma")
        n = data["n"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise ValueError("scale.n must be an integer >= 2")
        self.n_ = n
        return self

    @property
    def uses_layer_sigma(self) -> bool:
        """Whether `predict` reads `layer_sigma`."""
        check_fitted(self, "coef_")
        return "log_layer_sigma" in self.features_

    @property
    def uses_image_size(self) -> bool:
        """Whether `predict` reads `image_size`."""
        check_fitted(self, "coef_")
        return "at_border" in self.features_

    def _design(self, det: np.ndarray, score: object, layer_sigma: object,
                image_size: object) -> np.ndarray:
        """φ `[N, 4, F]` of checked boxes `det [N, 4]` (the terms of `features_`)."""
        n = len(det)
        p = as_float_array("score", score, ndim=1)
        check_length("score", p, n, "boxes")
        if not ((p >= 0) & (p <= 1)).all():
            raise FieldError("score", "score must be in [0, 1]", row=int(np.argmax(~(
                (p >= 0) & (p <= 1)))))
        p = np.clip(p, 1e-6, 1 - 1e-6)
        per_edge: list[np.ndarray] = []     # [N, 4] each
        wh = np.log(np.maximum(det[:, 2:], _TINY))                   # [N, 2]
        along = wh[:, [0, 1, 0, 1]]           # x edges: the width; y edges: the height
        across = wh[:, [1, 0, 1, 0]]
        per_edge += [along, across, np.repeat(np.log(p / (1 - p))[:, None], 4, axis=1)]
        if "log_layer_sigma" in self.features_:
            if layer_sigma is None:
                raise FieldError("layer_boxes", "these box regions read the spread of the "
                                                "decoder layers' boxes: send each detection's "
                                                "layer_boxes, L >= 2 boxes [x, y, w, h]", row=0)
            per_edge.append(np.log(_sigma(layer_sigma, n) + self.sigma_floor_))
        if "at_border" in self.features_:
            if image_size is None:
                raise FieldError("image_size", "these box regions read where the box meets its "
                                               "image's border: give each image's width and "
                                               "height")
            per_edge.append(_at_border(det, image_size))
        eye = np.broadcast_to(np.eye(4), (n, 4, 4))
        return np.concatenate([eye, np.stack(per_edge, axis=2)], axis=2)


_ALL_TERMS = ("edge", "log_along", "log_across", "score_logit", "log_layer_sigma", "at_border")


def _terms(layered: bool, bordered: bool) -> list[str]:
    return ["edge", "log_along", "log_across", "score_logit",
            *(["log_layer_sigma"] if layered else []), *(["at_border"] if bordered else [])]


def _width(features: list[str]) -> int:
    return 4 + len(features) - 1                      # `edge` is 4 intercepts


def _sigma(value: object, n: int) -> np.ndarray:
    sig = as_float_array("layer_sigma", value, ndim=2)
    if sig.shape[1:] != (4,):
        raise FieldError("layer_sigma", f"layer_sigma must have shape [N, 4], got {sig.shape}")
    check_length("layer_sigma", sig, n, "boxes")
    if not (sig >= 0).all():
        raise FieldError("layer_sigma", "layer_sigma must be >= 0",
                         row=int(np.argmax(~(sig >= 0).all(axis=1))))
    return sig


def _at_border(det: np.ndarray, image_size: object) -> np.ndarray:
    """`[N, 4]` 1.0 where the edge lies within `BORDER_PX` of its image's border."""
    size = as_float_array("image_size", image_size, ndim=2)
    if size.shape[1:] != (2,):
        raise FieldError("image_size", f"image_size must have shape [N, 2] (width, height), "
                                       f"got {size.shape}")
    check_length("image_size", size, len(det), "boxes")
    e = box_edges(det)
    return np.stack([e[:, 0] <= BORDER_PX, e[:, 1] <= BORDER_PX,
                     e[:, 2] >= size[:, 0] - BORDER_PX, e[:, 3] >= size[:, 1] - BORDER_PX],
                    axis=1).astype(np.float64)


def _positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < 1e300:
        raise ValueError(f"scale.{name} must be a number > 0, got {value!r}")
    return float(value)
