"""The score stage of a streamed fit (`calibrators.fit._stream`), from the parts' summed
`ScoreTable`s: every candidate fit on the training part's table and scored on the
calibration part's, κ chosen the same way, the chosen method refit on both, as
`fit_score_stage` does in memory (the same functions, on tables instead of dumps).

A fit of at most `EXACT_ROWS` detections tabulates its rows as they are: the stage is then
the in-memory one to float rounding (rows summed in another order). A larger fit tabulates
the counts of `ScoreTable`'s cells (logits on a 1/256 grid, distances on 1 m), so every
calibrator is the exact fit of data whose logits moved by less than 1/256 to their cell's
mean; docs/science.md ("Streamed fit") gives what that changes, measured.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.special import expit

from calibrators.fit._options import FitOptions
from calibrators.fit._score_stage import (
    ScoreFit,
    candidate_names,
    choose_score_method,
    fit_classwise,
    score_fit,
)
from calibrators.scores import ScoreTable

__all__ = ["ScoreTables", "stream_scores"]


class ScoreTables(NamedTuple):
    """The `ScoreTable`s of the training part and of the calibration part (None: none)."""

    train: ScoreTable
    calib: ScoreTable | None

    def __add__(self, other: object) -> ScoreTables:   # type: ignore[override]
        if not isinstance(other, ScoreTables):
            return NotImplemented
        calib = None if self.calib is None or other.calib is None \
            else self.calib + other.calib
        return ScoreTables(self.train + other.train, calib)


def stream_scores(opts: FitOptions, tables: ScoreTables, temperature: float,
                  train_temperature: Callable[[], float]) -> ScoreFit:
    """The score stage from the summed tables; `temperature` is the global T of all fit rows
    (streamed), `train_temperature()` that of the training part alone (sigmoid: the `auto`
    temperature candidate, whose calibration probabilities are `sigmoid(z / T)` of the
    labelled logits the tables hold)."""
    names = candidate_names(opts.score_method, tables.calib is not None)

    def temperature_p() -> np.ndarray:
        assert tables.calib is not None   # a candidate is scored only on a calibration part
        return expit(tables.calib.rows().z / train_temperature())

    chosen, candidates, kappa, kappas = choose_score_method(
        names, tables.train, tables.calib, temperature_p, opts.min_samples, opts.score_shrink)
    full = tables.train if tables.calib is None else tables.train + tables.calib
    fitted = None if chosen == "temperature" else fit_classwise(chosen, full,
                                                                opts.min_samples, kappa)
    return score_fit(chosen, temperature, fitted, candidates, kappa, kappas)
