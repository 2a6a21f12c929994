"""The typed before/after summary: `Summary` (one set of detections) and `ProfileReport` (a
profile's `report`: the fit part and the held-out part).

Frozen dataclasses whose `to_dict()` is the stable JSON form stored in a profile (keys and
order as documented in `calibrators.evaluation`) and whose `from_dict()` reads it back, so the
dashboard, the CLI table and the detectors' report read fields, not dictionary keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["ClassSummary", "Counts", "CoverageSummary", "Pair", "ProfileReport",
           "RegressionSummary", "Summary"]


def _get(data: Any, key: str, where: str) -> Any:
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be an object, got {type(data).__name__}")
    if key not in data:
        raise ValueError(f"{where} is missing key {key!r}")
    return data[key]


@dataclass(frozen=True)
class Pair:
    """A metric before and after calibration (either may be None: undefined or no profile)."""

    before: Any
    after: Any

    def to_dict(self) -> dict[str, Any]:
        return {"before": self.before, "after": self.after}

    @classmethod
    def from_dict(cls, data: Any, where: str = "pair") -> Pair:
        return cls(_get(data, "before", where), _get(data, "after", where))


@dataclass(frozen=True)
class Counts:
    """Frames, detections, ground-truth boxes, and TP / FP / FN at the matching threshold."""

    frames: int
    detections: int
    ground_truth: int
    tp: int
    fp: int
    fn: int

    def to_dict(self) -> dict[str, int]:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, data: Any) -> Counts:
        return cls(**{k: int(_get(data, k, "counts")) for k in cls.__dataclass_fields__})


@dataclass(frozen=True)
class CoverageSummary:
    """Share of TPs inside the Mahalanobis balls of `radii` (σ), nominal χ²_D share, before and
    after (`[len(radii)]` each or None)."""

    radii: list[float]
    nominal: list[float]
    before: list[float] | None
    after: list[float] | None

    def to_dict(self) -> dict[str, Any]:
        return {"radii": self.radii, "nominal": self.nominal, "before": self.before,
                "after": self.after}

    @classmethod
    def from_dict(cls, data: Any) -> CoverageSummary:
        return cls(*(_get(data, k, "regression.coverage")
                     for k in ("radii", "nominal", "before", "after")))


@dataclass(frozen=True)
class RegressionSummary:
    """Regression metrics of the n TPs' residuals under Σ before / after; `note_*` say why a
    side is undefined (no covariance, singular Σ, no profile)."""

    n: int
    nll: Pair
    mean_md: Pair
    expected_md: float
    coverage: CoverageSummary
    miscalibration_area: dict[str, Pair]
    note_before: str | None
    note_after: str | None

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "nll": self.nll.to_dict(), "mean_md": self.mean_md.to_dict(),
                "expected_md": self.expected_md, "coverage": self.coverage.to_dict(),
                "miscalibration_area": {k: v.to_dict()
                                        for k, v in self.miscalibration_area.items()},
                "note_before": self.note_before, "note_after": self.note_after}

    @classmethod
    def from_dict(cls, data: Any) -> RegressionSummary:
        w = "regression"
        area = _get(data, "miscalibration_area", w)
        return cls(n=int(_get(data, "n", w)),
                   nll=Pair.from_dict(_get(data, "nll", w), f"{w}.nll"),
                   mean_md=Pair.from_dict(_get(data, "mean_md", w), f"{w}.mean_md"),
                   expected_md=float(_get(data, "expected_md", w)),
                   coverage=CoverageSummary.from_dict(_get(data, "coverage", w)),
                   miscalibration_area={str(k): Pair.from_dict(v, f"{w}.miscalibration_area")
                                        for k, v in area.items()},
                   note_before=_get(data, "note_before", w),
                   note_after=_get(data, "note_after", w))


@dataclass(frozen=True)
class ClassSummary:
    """One class: detections n, TPs, its k (and whether pooled), ECE and regression NLL before
    and after. `name` is the `class` key of the dict form."""

    name: str
    n: int
    tp: int
    k: float | None
    fallback: bool | None
    ece_before: float | None
    ece_after: float | None
    nll_before: float | None
    nll_after: float | None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"class": self.name}
        out.update({k: getattr(self, k) for k in list(self.__dataclass_fields__)[1:]})
        return out

    @classmethod
    def from_dict(cls, data: Any) -> ClassSummary:
        keys = list(cls.__dataclass_fields__)[1:]
        return cls(str(_get(data, "class", "per_class")),
                   *(_get(data, k, "per_class") for k in keys))


@dataclass(frozen=True)
class Summary:
    """Before/after calibration metrics of one set of detections (see `calibrators.evaluation`).

    classification: {ece, mce, dece, nll, brier} -> Pair; plots: the plot series as the
    module docstring of `calibrators.evaluation` lists them (plain JSON, drawn by the dashboard);
    regions (with a profile serving ellipses): {method, levels [Q], coverage: the
    `metrics.CoverageTable` dict (overall [Q] and rows per class × distance bin), mean_area [Q]
    m² (None: unbounded, a level above what the conformal groups certify),
    gaussian_coverage [Q]: what χ²₂ radii would cover on the same Σ'}.
    """

    schema: int
    threshold: float
    score_mode: str
    cov_source: str
    dims: tuple[str, ...]
    temperature: float | None
    counts: Counts
    classification: dict[str, Pair]
    regression: RegressionSummary
    per_class: tuple[ClassSummary, ...]
    plots: dict[str, Any]
    regions: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The stable JSON form (the dict a profile's report stores)."""
        return {"schema": self.schema, "threshold": self.threshold,
                "score_mode": self.score_mode, "cov_source": self.cov_source,
                "dims": list(self.dims), "temperature": self.temperature,
                "counts": self.counts.to_dict(),
                "classification": {k: v.to_dict() for k, v in self.classification.items()},
                "regression": self.regression.to_dict(),
                "per_class": [row.to_dict() for row in self.per_class],
                "plots": self.plots,
                **({} if self.regions is None else {"regions": self.regions})}

    @classmethod
    def from_dict(cls, data: Any) -> Summary:
        """Read the dict form back; a ValueError names a missing key."""
        w = "summary"
        cls_part = _get(data, "classification", w)
        return cls(schema=int(_get(data, "schema", w)),
                   threshold=float(_get(data, "threshold", w)),
                   score_mode=str(_get(data, "score_mode", w)),
                   cov_source=str(_get(data, "cov_source", w)),
                   dims=tuple(_get(data, "dims", w)),
                   temperature=_get(data, "temperature", w),
                   counts=Counts.from_dict(_get(data, "counts", w)),
                   classification={str(k): Pair.from_dict(v, f"classification.{k}")
                                   for k, v in cls_part.items()},
                   regression=RegressionSummary.from_dict(_get(data, "regression", w)),
                   per_class=tuple(ClassSummary.from_dict(r)
                                   for r in _get(data, "per_class", w)),
                   plots=_get(data, "plots", w), regions=data.get("regions"))


@dataclass(frozen=True)
class ProfileReport:
    """A profile's `report`: the summary on the fit part, on the held-out part (None without
    a hold-out), the `min_score` filter and the matching `threshold` of the fit, and (fits
    with stages) `selection`: per stage the chosen method and every candidate's held-out
    score, `{"score": {"chosen", "candidates": {method: {"nll", "ece"}}}, "covariance":
    {"chosen", "candidates": {method: {"nll"}}}, "regions": {"chosen", "calibration_tps"}}`."""

    fit: Summary
    holdout: Summary | None
    min_score: float | None
    threshold: float
    selection: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        out = {"fit": self.fit.to_dict(),
               "holdout": None if self.holdout is None else self.holdout.to_dict(),
               "min_score": self.min_score, "threshold": self.threshold}
        if self.selection is not None:
            out["selection"] = self.selection
        return out

    @classmethod
    def from_dict(cls, data: Any) -> ProfileReport | None:
        """The report of a profile's `report` dict, or None for an empty one (a profile built
        by hand has no report)."""
        if data == {}:
            return None
        held = _get(data, "holdout", "report")
        return cls(fit=Summary.from_dict(_get(data, "fit", "report")),
                   holdout=None if held is None else Summary.from_dict(held),
                   min_score=_get(data, "min_score", "report"),
                   threshold=float(_get(data, "threshold", "report")),
                   selection=data.get("selection"))
