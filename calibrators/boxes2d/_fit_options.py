"""`FitOptions2D`: every option of a 2-D profile fit (`fit_profile_2d`), typed and validated
once, as `calibrators.fit.FitOptions` is for 3-D fits.

The names it shares with `FitOptions` (`holdout`, `seed`, `calibration`, `score_method`,
`min_samples`, `min_group`) mean the same and have the same defaults, with images in place of
frames; the front ends (`detcal fit --from coco`, `POST /v1/fit` with a COCO pair) build their
flags and form fields from `describe()`. A bad value raises `OptionError` naming the option.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from calibrators.boxes2d._box_scores import REGION_SCORES
from calibrators.boxes2d._layer_spread import MIN_SIGMA
from calibrators.core.errors import OptionError
from calibrators.core.vocab import SCORE_METHODS, SCORE_MODES
from calibrators.fit import (
    OptionSpec,
    describe_options,
    option_integer,
    option_number,
    options_from_dict,
)

__all__ = ["SCORE_METHODS_2D", "FitOptions2D"]

#: The score calibrators a 2-D fit tries: one temperature on the label's logit, the per-class
#: calibrators of `calibrators.scores` (all but the range term, which needs a distance), and
#: the position-dependent logistic calibrator (`PositionCalibrator`).
SCORE_METHODS_2D: tuple[str, ...] = (*(m for m in SCORE_METHODS if m != "platt_range"),
                                     "position")


def _opt(default: Any, help: str, type_: type, choices: tuple[str, ...] | None = None,
         nullable: bool = False) -> Any:
    return field(default=default, metadata={"help": help, "type": type_, "choices": choices,
                                             "nullable": nullable})


@dataclass(frozen=True)
class FitOptions2D:
    """Options of `fit_profile_2d` (docs/boxes2d.md, "A 2-D profile").

    iou_threshold: a detection is a true positive when it takes a ground truth at IoU >= this
    (the COCO rule, `match_labels`). holdout: fraction of the images, in [0, 1), kept for the
    report. calibration: fraction of the other images, in [0, 1), kept apart to choose the
    score calibrator and to calibrate the box regions (0: no choice, `auto` is `temperature`,
    and no regions). seed: the seed of both image splits. score_method: one of
    `SCORE_METHODS_2D`, or `auto`: the lowest held-out NLL on the calibration part.
    score_mode: `sigmoid` or `softmax`, how to read the detections' `logits` (required with
    logits, unused without: the score's logit is calibrated). region_score: the conformity
    score of the box regions, `additive` (pixels), `scaled` (pixels over the edge σ from
    the decoder layers' spread, which needs `layer_boxes` with L >= 2), `adaptive` (pixels
    over the edge-error scale `EdgeErrorScale` fit on the fitting part's true positives: box
    extent, score, layer spread when given, image border), or `auto`: adaptive when the
    fitting part holds at least `MIN_SCALE_FIT` true positives, else scaled with layer
    boxes, else additive. min_sigma: the floor of each edge's σ (pixels, scaled regions).
    min_samples: detections a class needs for its own score calibrator (else the pooled one).
    min_group: calibration true positives a class × size cell needs for its own region radius.
    """

    iou_threshold: float = _opt(0.5, "COCO IoU a true positive reaches, in [0, 1]", float)
    holdout: float = _opt(0.0, "fraction of images held out for the report, in [0, 1)", float)
    calibration: float = _opt(0.5, "fraction of the fit images kept apart to choose the score "
                              "calibrator and calibrate the box regions, in [0, 1)", float)
    seed: int = _opt(0, "seed of the image splits", int)
    score_method: str = _opt("auto", "score calibration: one temperature, per class, or "
                             "per class with box-position terms (position)", str,
                             ("auto", *SCORE_METHODS_2D))
    score_mode: str | None = _opt(None, "how the detections' logits read: sigmoid or softmax "
                                  "(none: no logits, the score is calibrated)", str,
                                  SCORE_MODES, nullable=True)
    region_score: str = _opt("auto", "box regions: additive pixels, scaled by each edge's σ "
                             "across decoder layers, or adaptive: scaled by a fitted edge-error "
                             "scale (auto: adaptive)", str, ("auto", *REGION_SCORES))
    min_sigma: float = _opt(MIN_SIGMA, "floor of each box edge's σ in pixels (scaled regions)",
                            float)
    min_samples: int = _opt(50, "detections a class needs for its own score calibrator", int)
    min_group: int = _opt(100, "calibration true positives a class × size cell needs for its "
                          "own region radius", int)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "iou_threshold", _fraction("iou_threshold", self.iou_threshold, 1.0, True))
        for name in ("holdout", "calibration"):
            set_(self, name, _fraction(name, getattr(self, name), 1.0, False))
        set_(self, "seed", option_integer("seed", self.seed, 0))
        for name, choices in (("score_method", ("auto", *SCORE_METHODS_2D)),
                              ("region_score", ("auto", *REGION_SCORES))):
            if getattr(self, name) not in choices:
                raise OptionError(name, f"{name} must be one of {list(choices)}, got "
                                        f"{getattr(self, name)!r}")
        if self.score_mode is not None and self.score_mode not in SCORE_MODES:
            raise OptionError("score_mode", f"score_mode must be one of {list(SCORE_MODES)} "
                                            f"or none, got {self.score_mode!r}")
        sigma = option_number("min_sigma", self.min_sigma)
        if sigma <= 0:
            raise OptionError("min_sigma", f"min_sigma must be > 0 pixels, got {sigma}")
        set_(self, "min_sigma", sigma)
        set_(self, "min_samples", option_integer("min_samples", self.min_samples, 1))
        set_(self, "min_group", option_integer("min_group", self.min_group, 1))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict; `FitOptions2D.from_dict` reads it back."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FitOptions2D:
        """Options from a dict of some or all fields (missing: defaults); an unknown key is an
        OptionError naming it."""
        return options_from_dict(cls, data, "2-D fit option")

    @classmethod
    def describe(cls) -> tuple[OptionSpec, ...]:
        """One `OptionSpec` per option, in declaration order (for CLI flags and form fields)."""
        return describe_options(cls)


def _fraction(name: str, value: Any, high: float, closed: bool) -> float:
    """`value` as a number in [0, high] (`closed`) or [0, high), else an OptionError."""
    x = option_number(name, value)
    if not (0.0 <= x <= high if closed else 0.0 <= x < high):
        interval = f"[0, {high:g}]" if closed else f"[0, {high:g})"
        raise OptionError(name, f"{name} must be in {interval}, got {x}")
    return x
