"""`FitOptions`: every option of a profile fit, typed and validated once.

`fit_profile`, `POST /v1/fit`, the fit-job runner and `detcal fit` all take this one object:
the front ends build their flags and form fields from `FitOptions.describe()` (name, type,
default, choices, help), so a new option appears everywhere with one name and one default.
A bad value raises `OptionError` (a ValueError) whose `field` names the option.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, TypeVar

from calibrators.core.defaults import MATCH_THRESHOLD
from calibrators.core.errors import OptionError
from calibrators.core.vocab import (
    COV_METHODS,
    COV_SOURCE_CHOICES,
    REGION_CALIBRATIONS,
    REGION_METHODS,
    SCORE_METHODS,
    check_dims,
)
from calibrators.regions import check_distance_edges

__all__ = ["FitOptions", "OptionSpec", "option_integer", "option_number"]




@dataclass(frozen=True)
class OptionSpec:
    """How a front end presents one option: its name, value type (`float`, `int`, `bool`,
    `str`), default as the front end spells it (dims: `"x,y"`), allowed values (or None),
    whether None is allowed, and help text."""

    name: str
    type: type
    default: Any
    choices: tuple[str, ...] | None
    nullable: bool
    help: str


def _opt(default: Any, help: str, type_: type, choices: tuple[str, ...] | None = None,
         nullable: bool = False) -> Any:
    return field(default=default, metadata={"help": help, "type": type_, "choices": choices,
                                             "nullable": nullable})


@dataclass(frozen=True)
class FitOptions:
    """Options of `fit_profile` (defaults are the documented ones; see docs/science.md).

    threshold: matching distance in m (> 0). dims: regression box fields (`("x", "y")`; a
    string `"x,y"` is accepted). cov_source: `auto` | `given` | `layers` | `hypotheses` | `none`
    (`auto`: given if the dump has det_cov over `dims`, else layers if L >= 2, else none;
    `hypotheses`, the spread of the dump's det_hyp_boxes, only by name). holdout:
    fraction of frames in [0, 1) kept for the report. min_score: drop detections with a raw
    score below it (None: all queries). min_samples: matches a class needs for its own k
    (else the pooled k). seed: the hold-out split's seed. modulation: logits modulation before
    temperature scaling (needs L >= 2 decoder layers).
    score_method / cov_method / region_method: a method of `calibrators.core.vocab.SCORE_METHODS`
    / `COV_METHODS` / `REGION_METHODS`, or `auto`: the candidate with the best held-out score
    on the calibration part (score: binary NLL of the label's probability; covariance:
    regression NLL; region: conformal when the calibration part has `min_group` true
    positives, else gaussian). calibration: fraction of the fit frames in [0, 1) kept apart for
    those choices and the conformal radii (0: none; `auto` then means the thesis methods).
    min_group: calibration TPs a class × distance group needs for its own conformal radius.
    distance_edges: inner edges (m) of the conformal distance bins. other_sources: also fit
    the covariance and region stages for the other covariance sources the dump allows.
    cell_floors: a cell the conformal partition serves from a larger group (merged bins,
    pooled classes), whose own scores show the group's radius too small for it, is served at
    least its own conformal radius; floor_delta: at levels >= 80 %, at least its own
    training-conditional radius at this δ. region_delta: None, or the
    training-conditional conformal radii (each served cell covers its level with probability
    >= 1 - region_delta over the calibration draw); `calibrators.regions` explains both.
    cell_ceilings: with cell floors, a cell whose own scores show its group's radius too wide
    for it is served its own radius. region_calibration: `cross` (the conformal radii from
    every fit true positive: each part's scores under the Σ' fit on the other part, the radii
    served with the Σ' fit on the whole fit part; `calibrators.fit._cross`) or `split` (from
    the calibration part's true positives under the Σ' fit on the training part).
    """

    threshold: float = _opt(MATCH_THRESHOLD, "matching distance in m", float)
    dims: tuple[str, ...] = _opt(("x", "y"), "regression box fields, comma separated", str)
    cov_source: str = _opt("auto", "raw covariance: the dump's det_cov (given), the spread "
                           "across decoder layers (layers), the spread of the group heads' box "
                           "hypotheses (hypotheses), none, or auto", str,
                           COV_SOURCE_CHOICES)
    holdout: float = _opt(0.0, "fraction of frames held out for the report, in [0, 1)", float)
    min_score: float | None = _opt(None, "only detections with a raw score >= this take part "
                                   "(none: all queries)", float, nullable=True)
    min_samples: int = _opt(50, "matches a class needs for its own k", int)
    seed: int = _opt(0, "seed of the hold-out split", int)
    modulation: bool = _opt(False, "logits modulation before temperature scaling (needs the "
                            "logits of every decoder layer, L >= 2)", bool)
    score_method: str = _opt("auto", "score calibration: one temperature, or per class", str,
                             ("auto", *SCORE_METHODS))
    cov_method: str = _opt("auto", "covariance scaling: Σ + k·d·I (depth) or s·Σ + k·d·I "
                           "(shrinkage), per class", str, ("auto", *COV_METHODS))
    region_method: str = _opt("auto", "uncertainty regions: Gaussian χ² radii or split-"
                              "conformal radii per class × distance bin", str,
                              ("auto", *REGION_METHODS))
    calibration: float = _opt(0.5, "fraction of the fit frames kept apart to choose the "
                              "auto methods and calibrate the conformal radii, in [0, 1)", float)
    min_group: int = _opt(100, "calibration TPs a class × distance group needs for its own "
                          "conformal radius", int)
    distance_edges: tuple[float, ...] = _opt((15.0, 30.0), "inner edges of the conformal "
                                             "distance bins in m, comma separated", str)
    other_sources: bool = _opt(True, "also fit the covariance and region stages for every "
                               "other covariance source the dump allows, so a request is "
                               "calibrated with whatever it carries", bool)
    cell_floors: bool = _opt(True, "conformal regions: a class × distance cell served by a "
                             "larger group that is too small for it gets at least its own "
                             "conformal radius", bool)
    region_delta: float | None = _opt(None, "conformal regions: every served cell covers at "
                                      "least its level with probability >= 1 - region_delta "
                                      "over the calibration draw (none: on average)", float,
                                      nullable=True)
    score_shrink: float | None = _opt(None, "per-class score calibrators: a class with n true "
                                      "positives serves n/(n + score_shrink) of its own fit "
                                      "and the rest of the pooled one (none: chosen on the "
                                      "calibration part by held-out NLL)", float,
                                      nullable=True)
    floor_delta: float | None = _opt(0.2, "conformal regions with cell floors: at levels of "
                                     "0.8 and above every cell floor serves at least the "
                                     "cell's own "
                                     "radius that covers its level with probability >= "
                                     "1 - floor_delta (none: only where a test shows its "
                                     "group's radius too small)", float, nullable=True)

    region_calibration: str = _opt("cross", "conformal regions: radii from the calibration "
                                   "part's true positives (split), or from every fit true "
                                   "positive, each part scored under the covariance fit on "
                                   "the other and served with the one fit on all (cross)",
                                   str, REGION_CALIBRATIONS)
    cell_ceilings: bool = _opt(True, "conformal regions with cell floors: a class × distance "
                               "cell whose own true positives show its group's radius "
                               "covering more than the level is served its own conformal "
                               "radius", bool)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "threshold", option_number("threshold", self.threshold))
        if self.threshold <= 0:
            raise OptionError("threshold", f"threshold must be a finite distance > 0 m, got "
                                           f"{self.threshold}")
        try:
            set_(self, "dims", check_dims(self.dims))
        except ValueError as exc:
            raise OptionError("dims", str(exc)) from None
        if self.cov_source not in COV_SOURCE_CHOICES:
            raise OptionError("cov_source", f"cov_source must be one of "
                                            f"{list(COV_SOURCE_CHOICES)}, got {self.cov_source!r}")
        set_(self, "holdout", option_number("holdout", self.holdout))
        if not 0.0 <= self.holdout < 1.0:
            raise OptionError("holdout", f"holdout must be a fraction of frames in [0, 1), got "
                                         f"{self.holdout}")
        if self.min_score is not None:
            set_(self, "min_score", option_number("min_score", self.min_score))
            if not 0.0 <= self.min_score <= 1.0:
                raise OptionError("min_score", f"min_score must be a probability in [0, 1], "
                                               f"got {self.min_score}")
        set_(self, "min_samples", option_integer("min_samples", self.min_samples, minimum=1))
        set_(self, "seed", option_integer("seed", self.seed, minimum=0))
        if not isinstance(self.modulation, bool):
            raise OptionError("modulation", f"modulation must be True or False, got "
                                            f"{self.modulation!r}")
        for name, choices in (("score_method", SCORE_METHODS), ("cov_method", COV_METHODS),
                              ("region_method", REGION_METHODS)):
            if getattr(self, name) not in ("auto", *choices):
                raise OptionError(name, f"{name} must be one of {['auto', *choices]}, got "
                                        f"{getattr(self, name)!r}")
        if self.region_calibration not in REGION_CALIBRATIONS:
            raise OptionError("region_calibration", f"region_calibration must be one of "
                                                    f"{list(REGION_CALIBRATIONS)}, got "
                                                    f"{self.region_calibration!r}")
        set_(self, "calibration", option_number("calibration", self.calibration))
        if not 0.0 <= self.calibration < 1.0:
            raise OptionError("calibration", f"calibration must be a fraction of frames in "
                                             f"[0, 1), got {self.calibration}")
        set_(self, "min_group", option_integer("min_group", self.min_group, minimum=1))
        set_(self, "distance_edges", _edges(self.distance_edges))
        for name in ("other_sources", "cell_floors", "cell_ceilings"):
            if not isinstance(getattr(self, name), bool):
                raise OptionError(name, f"{name} must be True or False, got "
                                        f"{getattr(self, name)!r}")
        if self.score_shrink is not None:
            set_(self, "score_shrink", option_number("score_shrink", self.score_shrink))
            if not 0.0 <= self.score_shrink < math.inf:
                raise OptionError("score_shrink", f"score_shrink must be a finite number >= 0 "
                                                  f"or none, got {self.score_shrink}")
        for name in ("region_delta", "floor_delta"):
            if getattr(self, name) is not None:
                set_(self, name, option_number(name, getattr(self, name)))
                if not 0.0 < getattr(self, name) < 1.0:
                    raise OptionError(name, f"{name} must be in (0, 1) or none, got "
                                            f"{getattr(self, name)}")

    def conformal_options(self) -> dict[str, Any]:
        """The keyword options of the conformal radii (`calibrators.fit.conformal_region_fit`,
        `ConformalRegions`) that these options ask for."""
        return {"cell_floor": self.cell_floors, "delta": self.region_delta,
                "floor_delta": self.floor_delta, "cell_ceiling": self.cell_ceilings}

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (dims as a list); `FitOptions.from_dict` reads it back."""
        out = asdict(self)
        out["dims"] = list(self.dims)
        out["distance_edges"] = list(self.distance_edges)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FitOptions:
        """Options from a dict of some or all fields (missing: defaults); an unknown key is an
        OptionError naming it."""
        return options_from_dict(cls, data, "fit option")

    @classmethod
    def describe(cls) -> tuple[OptionSpec, ...]:
        """One `OptionSpec` per option, in declaration order (for CLI flags and form fields)."""
        return describe_options(cls)


def option_number(name: str, value: Any) -> float:
    """`value` as a finite float (numpy scalars too, not a bool or a string), else an
    OptionError naming the option `name`."""
    if isinstance(value, bool | str):
        raise OptionError(name, f"{name} must be a number, got {value!r}")
    try:   # numpy scalars too
        x = float(value)
    except (TypeError, ValueError):
        raise OptionError(name, f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise OptionError(name, f"{name} must be finite, got {value!r}")
    return x


def option_integer(name: str, value: Any, minimum: int) -> int:
    """`value` as an int >= `minimum` (a whole number of any numeric type, not a bool or a
    string), else an OptionError naming the option `name`."""
    try:
        as_int = int(value)
        whole = not isinstance(value, bool | str) and as_int == value
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole or as_int < minimum:
        raise OptionError(name, f"{name} must be an integer >= {minimum}, got {value!r}")
    return as_int


def _edges(value: Any) -> tuple[float, ...]:
    """Inner distance-bin edges: `"15,30"` or numbers, increasing and > 0 (may be empty)."""
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",") if v.strip()]
    try:
        edges = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise OptionError("distance_edges", f"distance_edges must be numbers in m, got "
                                            f"{value!r}") from None
    try:
        check_distance_edges((0.0, *edges, float("inf")), name="distance_edges")
    except ValueError as exc:
        raise OptionError("distance_edges", f"distance_edges must increase from > 0 m: "
                                            f"{exc}") from None
    return edges


_O = TypeVar("_O")


def options_from_dict(cls: type[_O], data: Any, what: str) -> _O:
    """The options dataclass `cls` from a dict of some or all of its fields (missing:
    defaults); OptionError naming `options` for a non-dict, or an unknown key (a `what`)."""
    if not isinstance(data, dict):
        raise OptionError("options", f"options must be an object, got {type(data).__name__}")
    names = {f.name for f in fields(cls)}   # type: ignore[arg-type]
    for key in data:
        if key not in names:
            raise OptionError(str(key), f"unknown {what} {key!r}; known: {sorted(names)}")
    return cls(**data)


def describe_options(cls: type) -> tuple[OptionSpec, ...]:
    """One `OptionSpec` per field of the options dataclass `cls` (declared with `_opt`), in
    declaration order; a tuple default is written as its comma-separated text."""
    return tuple(OptionSpec(name=f.name, type=f.metadata["type"],
                            default=",".join(f"{v:g}" if isinstance(v, float) else v
                                             for v in f.default)
                            if isinstance(f.default, tuple) else f.default,
                            choices=f.metadata["choices"], nullable=f.metadata["nullable"],
                            help=f.metadata["help"]) for f in fields(cls))
