"""The score stage of a fit: fit each candidate score calibrator, pick one by held-out NLL.

A candidate is one of `calibrators.core.vocab.SCORE_METHODS`: the global temperature of the
thesis (`p = σ(z / T)` / `softmax(z / T)`), or a per-class calibrator of the label's logit
(`calibrators.scores`). Every candidate is fit on the training part and scored
on the calibration part (frames kept apart) by the binary NLL and ECE of the label's
probability against TP; `auto` picks the lowest NLL. A per-class method's shrinkage toward
its pooled fit (`shrink` κ, `calibrators.scores`) is chosen the same way from `SHRINK_GRID`
(its training-part fit served with each κ), unless the options fix it. The chosen method is
then refit on the training and calibration parts together. The label of a detection never
changes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.special import expit

from calibrators import metrics
from calibrators.core.json_safe import to_jsonable
from calibrators.core.selection import choose_lowest_nll
from calibrators.core.vocab import SCORE_METHODS
from calibrators.data import Dump
from calibrators.evaluation import ts_labels, ts_logits
from calibrators.scores import (
    ScoreRows,
    ScoreTable,
    TemperatureScaler,
    label_logit,
    make_score_calibrator,
)

__all__ = ["SHRINK_GRID", "ScoreFit", "candidate_names", "choose_score_method",
           "fit_classwise", "fit_score_stage", "score_fit", "score_table"]

#: The shrinkage strengths κ (pseudo-counts of true positives) a fit chooses among.
SHRINK_GRID = (0.0, 10.0, 30.0, 100.0, 300.0, 1000.0)


@dataclass(frozen=True)
class ScoreFit:
    """The fitted score stage: `method`, the global `temperature` (always fit: the thesis
    baseline, and what `temperature` serves), the per-class calibrator's dict form (None for
    `temperature`), and each candidate's held-out `{"nll", "ece"}` (empty without a
    calibration part), the per-class shrinkage `shrink` and each κ's held-out NLL (empty
    when nothing was chosen)."""

    method: str
    temperature: float
    params: dict[str, Any] | None
    candidates: dict[str, dict[str, float]] = field(default_factory=dict)
    shrink: float = 0.0
    shrink_candidates: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types (`params` is already the calibrator's `to_dict()`)."""
        return to_jsonable(asdict(self))


def fit_score_stage(full: Dump, full_tp: np.ndarray, train: Dump, train_tp: np.ndarray,
                    calib: Dump | None, calib_tp: np.ndarray | None, method: str,
                    modulation: bool, min_samples: int, shrink: float | None = 0.0
                    ) -> ScoreFit:
    """Fit the score stage (module docstring); `method` is `auto` or a score method; `shrink`
    a per-class method's κ, or None to choose it on the calibration part (0 without one).

    `full` is the whole fit part, `train` and `calib` its frames split in two (calib None:
    no calibration part); `*_tp [N]` their TP masks.
    """
    held = calib is not None and calib_tp is not None
    names = candidate_names(method, held)
    on_train = score_table(train, train_tp, modulation)
    on_calib = score_table(calib, calib_tp, modulation) if held else None

    def temperature_p() -> np.ndarray:
        fitted = _fit_temperature(train, train_tp, modulation)
        return expit(label_logit(ts_logits(calib, modulation) / fitted.temperature_,
                                 calib.det_labels, calib.score_mode))

    chosen, candidates, kappa, kappas = choose_score_method(
        names, on_train, on_calib, temperature_p, min_samples, shrink)
    temperature = _fit_temperature(full, full_tp, modulation)
    fitted = None if chosen == "temperature" else fit_classwise(
        chosen, score_table(full, full_tp, modulation), min_samples, kappa)
    return score_fit(chosen, float(temperature.temperature_), fitted, candidates, kappa, kappas)


def candidate_names(method: str, held: bool) -> list[str]:
    """The score methods a fit with `method` tries (`held`: it has a calibration part)."""
    if method != "auto":
        return [method]
    return list(SCORE_METHODS) if held else ["temperature"]   # nothing to choose on


def choose_score_method(names: list[str], train: ScoreTable, calib: ScoreTable | None,
                        temperature_p: Callable[[], np.ndarray], min_samples: int,
                        shrink: float | None) -> tuple[str, dict[str, dict[str, float]],
                                                       float, dict[float, float]]:
    """`(method, each candidate's held-out {"nll", "ece"}, κ, each κ's held-out NLL)`:
    every candidate of `names` fit on the training part's table and scored on the
    calibration part's (`temperature_p()`: the global temperature's probabilities of the
    calibration rows, in `calib.rows()` order; a calibrator with a range term is fit and
    scored on the by-range cells), then κ chosen the same way when `shrink` is None (module
    docstring)."""
    candidates: dict[str, dict[str, float]] = {}
    on_train: dict[str, Any] = {}
    if calib is not None and len(names) > 1:
        def held_out(name: str) -> dict[str, float]:
            if name == "temperature":
                rows, p = calib.rows(), temperature_p()
            else:
                on_train[name] = fitted = fit_classwise(name, train, min_samples)
                rows = calib.rows(by_range=fitted.uses_distances)
                p = _transform(fitted, rows)
            return {"nll": metrics.classification_nll(p, rows.hit, sample_weight=rows.weight),
                    "ece": metrics.expected_calibration_error(p, rows.hit,
                                                              sample_weight=rows.weight)}

        chosen, candidates = choose_lowest_nll(names, held_out)
    else:
        chosen = names[0]
    kappas: dict[float, float] = {}
    if shrink is None and calib is not None and chosen != "temperature":
        fitted = on_train.get(chosen) or fit_classwise(chosen, train, min_samples)
        kappas = _shrink_nll(fitted, calib.rows(by_range=fitted.uses_distances))
        shrink = min(kappas, key=lambda k: (kappas[k], float(k)))
    return chosen, candidates, float(shrink or 0.0), kappas


def score_fit(method: str, temperature: float, fitted: Any,
              candidates: dict[str, dict[str, float]], kappa: float,
              kappas: dict[float, float]) -> ScoreFit:
    """The `ScoreFit` of a chosen `method` (`fitted` its calibrator, None for temperature)."""
    return ScoreFit(method=method, temperature=temperature,
                    params=None if fitted is None else fitted.to_dict(),
                    candidates=candidates, shrink=0.0 if method == "temperature" else kappa,
                    shrink_candidates={str(k): v for k, v in kappas.items()})


def score_table(dump: Dump, tp: np.ndarray, modulation: bool, exact: bool = True,
                rows: np.ndarray | None = None) -> ScoreTable:
    """The `ScoreTable` of a dump's detections (those where `rows [N]`, when given): their
    labelled logit (of the temperature-scaling logits), class, outcome `tp [N]` and
    distance."""
    z = label_logit(ts_logits(dump, modulation), dump.det_labels, dump.score_mode)
    columns = (z, dump.det_labels, np.asarray(tp, dtype=bool), dump.det_distance)
    if rows is not None:
        columns = tuple(c[rows] for c in columns)
    return ScoreTable.build(*columns, len(dump.classes), exact=exact)


def fit_classwise(name: str, table: ScoreTable, min_samples: int, shrink: float = 0.0) -> Any:
    """The per-class calibrator `name` fit on a table's rows (weighted by their counts; the
    by-range cells for a calibrator with a range term)."""
    calibrator = make_score_calibrator(name, min_samples=min_samples, shrink=shrink)
    rows = table.rows(by_range=calibrator.uses_distances)
    return calibrator.fit(rows.z, rows.labels, rows.hit, table.n_classes,
                          distances=rows.distances, sample_weight=rows.weight)


def _shrink_nll(fitted: Any, rows: ScoreRows) -> dict[float, float]:
    """Held-out NLL of a per-class calibrator fit on the training part, served with each κ of
    `SHRINK_GRID` (the class weights depend on κ alone: no refit)."""
    out = {}
    for kappa in SHRINK_GRID:
        fitted.shrink = kappa
        out[kappa] = metrics.classification_nll(_transform(fitted, rows), rows.hit,
                                                sample_weight=rows.weight)
    fitted.shrink = 0.0
    return out


def _transform(fitted: Any, rows: ScoreRows) -> np.ndarray:
    """`[K]` calibrated probability of each row."""
    return fitted.transform(rows.z, rows.labels, distances=rows.distances)


def _fit_temperature(dump: Dump, tp: np.ndarray, modulation: bool) -> TemperatureScaler:
    return TemperatureScaler(mode=dump.score_mode).fit(ts_logits(dump, modulation),
                                                       ts_labels(dump, tp))
