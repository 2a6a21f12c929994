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

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.special import expit

from calibrators import metrics
from calibrators.core.json_safe import to_jsonable
from calibrators.core.vocab import SCORE_METHODS
from calibrators.data import Dump
from calibrators.evaluation import ts_labels, ts_logits
from calibrators.scores import TemperatureScaler, label_logit, make_score_calibrator

__all__ = ["SHRINK_GRID", "ScoreFit", "fit_score_stage"]

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
    names = list(SCORE_METHODS) if method == "auto" else [method]
    if method == "auto" and calib is None:
        names = ["temperature"]   # nothing to choose on: the thesis method
    candidates: dict[str, dict[str, float]] = {}
    on_train: dict[str, Any] = {}
    held = calib is not None and calib_tp is not None
    if held and len(names) > 1:
        target = np.asarray(calib_tp, dtype=bool)
        for name in names:
            on_train[name] = fitted = _fit(name, train, train_tp, modulation, min_samples)
            p = _predict(fitted, name, calib, modulation)
            candidates[name] = {"nll": metrics.classification_nll(p, target),
                                "ece": metrics.expected_calibration_error(p, target)}
        chosen = min(candidates, key=lambda n: candidates[n]["nll"])
    else:
        chosen = names[0]
    kappas: dict[str, float] = {}
    if shrink is None and held and chosen != "temperature":
        fitted = on_train.get(chosen) or _fit(chosen, train, train_tp, modulation, min_samples)
        kappas = _shrink_nll(fitted, chosen, calib, np.asarray(calib_tp, dtype=bool),
                             modulation)
        shrink = min(kappas, key=lambda k: (kappas[k], float(k)))
    kappa = float(shrink or 0.0)
    fitted = _fit(chosen, full, full_tp, modulation, min_samples, kappa)
    temperature = fitted if chosen == "temperature" else _fit("temperature", full, full_tp,
                                                              modulation, min_samples)
    return ScoreFit(method=chosen, temperature=float(temperature.temperature_),
                    params=None if chosen == "temperature" else fitted.to_dict(),
                    candidates=candidates, shrink=0.0 if chosen == "temperature" else kappa,
                    shrink_candidates={str(k): v for k, v in kappas.items()})


def _shrink_nll(fitted: Any, name: str, calib: Dump, target: np.ndarray, modulation: bool
                ) -> dict[float, float]:
    """Held-out NLL of a per-class calibrator fit on the training part, served with each κ of
    `SHRINK_GRID` (the class weights depend on κ alone: no refit)."""
    out = {}
    for kappa in SHRINK_GRID:
        fitted.shrink = kappa
        out[kappa] = metrics.classification_nll(_predict(fitted, name, calib, modulation),
                                                target)
    fitted.shrink = 0.0
    return out


def _fit(name: str, dump: Dump, tp: np.ndarray, modulation: bool, min_samples: int,
         shrink: float = 0.0) -> Any:
    if name == "temperature":
        return TemperatureScaler(mode=dump.score_mode).fit(ts_logits(dump, modulation),
                                                           ts_labels(dump, tp))
    z = label_logit(ts_logits(dump, modulation), dump.det_labels, dump.score_mode)
    return make_score_calibrator(name, min_samples=min_samples, shrink=shrink).fit(
        z, dump.det_labels, np.asarray(tp, dtype=bool), len(dump.classes),
        distances=dump.det_distance)


def _predict(fitted: Any, name: str, dump: Dump, modulation: bool) -> np.ndarray:
    """`[N]` calibrated probability of each detection's label."""
    logits = ts_logits(dump, modulation)
    if name == "temperature":
        z = label_logit(logits / fitted.temperature_, dump.det_labels, dump.score_mode)
        return expit(z)
    z = label_logit(logits, dump.det_labels, dump.score_mode)
    return fitted.transform(z, dump.det_labels, distances=dump.det_distance)
