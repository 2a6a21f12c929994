"""What every per-class binary score calibrator shares: validation, the per-class loop with
its pooled fallback, serving by class, and the plain-dict form a profile stores.

A subclass names its `method`, its hyper-parameters (`_hyper`), and two small functions:
`_fit_one(z [n], hit [n], d [n] | None, w [n] | None) -> params` (a float64 array; `w` the
rows' weights, None for unit weights, which every subclass fits exactly as before weights
existed) and
`_apply(params, z [m], d [m] | None) -> p [m]`, strictly increasing in `z` for fixed `d`.

Shrinkage (`shrink` = κ >= 0, every calibrator's last hyper-parameter): a class with `n`
true positives serves `w·p_class + (1 - w)·p_pooled` with `w = n / (n + κ)`, so a small class
leans on the pooled fit by its sample size (κ = 0: its own fit alone). Both terms increase in
`z`, so the blend does too.
"""

from __future__ import annotations

from typing import Any, ClassVar, Self, TypeVar

import numpy as np

from calibrators.core.bins import as_binary, check_n_bins, check_nonempty, check_weights
from calibrators.core.checks import (
    as_float_array,
    as_int_array,
    check_distances,
    check_fitted,
    check_index,
    check_length,
    check_min_samples,
)
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable

_T = TypeVar("_T")

class ClasswiseCalibrator:
    """Base of the per-class score calibrators (see the module docstring).

    Fitted attributes: `n_classes_` (C), `params_` (list [C] of float64 arrays, a fallback
    class holding the pooled ones), `pooled_params_`, `fallback_classes_` (list of class
    indices that took the pooled fit: fewer than `min_samples` detections, or fewer than
    `min_each` true or false positives), `n_samples_ [C]`, `n_positives_ [C]` (int64).
    """

    method: ClassVar[str] = ""
    _hyper: ClassVar[tuple[str, ...]] = ("min_samples", "min_each")
    _param_ndim: ClassVar[int] = 1

    min_samples: int
    min_each: int
    shrink: float = 0.0

    # -- subclass hooks ----------------------------------------------------------------------
    def _check_hyper(self) -> None:
        """Validate the subclass's own hyper-parameters (raise ValueError naming them)."""

    def _needs_distances(self) -> bool:
        return False

    def _fit_one(self, z: np.ndarray, hit: np.ndarray, d: np.ndarray | None,
                 w: np.ndarray | None) -> np.ndarray:
        raise NotImplementedError

    def _apply(self, params: np.ndarray, z: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        raise NotImplementedError

    def _derive(self) -> None:
        """Set readable fitted attributes from `params_` (after fit and from_dict)."""

    # -- public API ----------------------------------------------------------------------------
    def fit(self, z: np.ndarray, labels: np.ndarray, tp: np.ndarray, n_classes: int,
            distances: np.ndarray | None = None, sample_weight: np.ndarray | None = None
            ) -> Self:
        """Fit on the labelled class's logit `z [N]`, `labels [N]` in [0, n_classes), `tp [N]`
        (bool or 0/1: the detection is a true positive) and optionally `distances [N]` (m,
        >= 0; used only by a range term) and `sample_weight [N]` (>= 0: how many detections
        a row stands for, e.g. the cells of a `ScoreTable`; counts are then weighted sums);
        returns self."""
        min_samples = check_min_samples(self.min_samples)
        min_each = check_n_bins("min_each", self.min_each, minimum=1)
        check_shrink(self.shrink)
        self._check_hyper()
        c = check_n_bins("n_classes", n_classes, minimum=1)
        x, y, d = self._inputs(z, labels, distances, c)
        hit = as_binary("tp", tp, x.shape[0], "z")
        w = None if sample_weight is None else check_weights(sample_weight, x.shape[0], "z")
        if w is not None:   # rows of no weight take no part
            x, y, hit, d, w = (None if a is None else a[w > 0] for a in (x, y, hit, d, w))
        if hit.all() or not hit.any():
            raise FieldError("tp", "tp must hold both true and false positives to fit a score "
                             f"calibrator, got {int(hit.sum())} of {hit.shape[0]} true")
        pooled = self._fit_one(x, hit, d, w)
        n_samples = np.rint(np.bincount(y, weights=w, minlength=c)).astype(np.int64)
        n_pos = np.rint(np.bincount(y, weights=hit if w is None else hit * w,
                                    minlength=c)).astype(np.int64)
        params, fallback = [], []
        for k, rows in enumerate(_rows_by_class(y, c)):
            if (n_samples[k] < min_samples or n_pos[k] < min_each
                    or n_samples[k] - n_pos[k] < min_each):
                fallback.append(k)
                params.append(pooled)
            else:
                params.append(self._fit_one(x[rows], hit[rows], None if d is None else d[rows],
                                            None if w is None else w[rows]))
        self.n_classes_, self.params_, self.pooled_params_ = c, params, pooled
        self.fallback_classes_ = fallback
        self.n_samples_, self.n_positives_ = n_samples, n_pos
        self._derive()
        return self

    def transform(self, z: np.ndarray, labels: np.ndarray,
                  distances: np.ndarray | None = None) -> np.ndarray:
        """Calibrated probability `[N]` in (0, 1) that each detection, with logit `z [N]` for
        its label `labels [N]`, is a true positive; the label itself is never changed."""
        check_fitted(self, "params_")
        x, y, d = self._inputs(z, labels, distances, self.n_classes_, empty_ok=True)
        out = np.empty(x.shape[0])
        weights = self.class_weights()
        for k, rows in enumerate(_rows_by_class(y, self.n_classes_)):
            if rows.size:
                dk = None if d is None else d[rows]
                out[rows] = self._apply(self.params_[k], x[rows], dk)
                if weights[k] < 1.0:
                    pooled = self._apply(self.pooled_params_, x[rows], dk)
                    out[rows] = weights[k] * out[rows] + (1.0 - weights[k]) * pooled
        return out

    def class_weights(self) -> np.ndarray:
        """`[C]` weight of each class's own fit against the pooled one: `n / (n + shrink)` of
        its true positives (1 without shrinkage; a fallback class serves the pooled fit)."""
        check_fitted(self, "params_")
        kappa = check_shrink(self.shrink)
        if kappa == 0.0:
            return np.ones(self.n_classes_)
        n = self.n_positives_.astype(np.float64)
        return n / (n + kappa)

    def fit_transform(self, z: np.ndarray, labels: np.ndarray, tp: np.ndarray, n_classes: int,
                      distances: np.ndarray | None = None) -> np.ndarray:
        """`fit(...).transform(z, labels, distances)`."""
        return self.fit(z, labels, tp, n_classes, distances).transform(z, labels, distances)

    def to_dict(self) -> dict[str, Any]:
        """Strict-JSON-able plain dict; `from_dict(to_dict())` serves identical probabilities.
        A fallback class's entry in `classes` is None (it serves `pooled`)."""
        check_fitted(self, "params_")
        fallback = set(self.fallback_classes_)
        return to_jsonable({
            "method": self.method_name,
            # shrink is written only when set: calibrators fit without it keep their JSON
            "hyper": {name: getattr(self, name) for name in self._hyper
                      if name != "shrink" or self.shrink},
            "n_classes": self.n_classes_,
            "pooled": self.pooled_params_,
            "classes": [None if k in fallback else p for k, p in enumerate(self.params_)],
            "fallback_classes": self.fallback_classes_,
            "n_samples": self.n_samples_,
            "n_positives": self.n_positives_,
        })

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Self:
        """The fitted calibrator `to_dict` wrote; ValueError naming a missing or bad key."""
        self = unfitted(cls, data, "score calibrator")
        if self.method_name != dict_key(data, "method"):
            raise ValueError(f"method is {data['method']!r} but {cls.__name__} with these "
                             f"hyper-parameters is {self.method_name!r}")
        c = check_n_bins("n_classes", dict_key(data, "n_classes"), minimum=1)
        pooled = self._param_array("pooled", dict_key(data, "pooled"))
        entries = dict_key(data, "classes")
        if not isinstance(entries, list) or len(entries) != c:
            raise ValueError(f"classes must list {c} entries (n_classes), got {entries!r:.80}")
        self.params_ = [pooled if p is None else self._param_array(f"classes[{k}]", p)
                        for k, p in enumerate(entries)]
        self.fallback_classes_ = [k for k, p in enumerate(entries) if p is None]
        self.n_classes_, self.pooled_params_ = c, pooled
        self.n_samples_ = as_int_array("n_samples", dict_key(data, "n_samples"))
        self.n_positives_ = as_int_array("n_positives", dict_key(data, "n_positives"))
        self._derive()
        return self

    @property
    def uses_distances(self) -> bool:
        """Whether `fit` and `transform` need distances (a range term)."""
        return self._needs_distances()

    @property
    def method_name(self) -> str:
        """The factory name of this calibrator (`make_score_calibrator`)."""
        return self.method

    # -- helpers -------------------------------------------------------------------------------
    def _inputs(self, z: object, labels: object, distances: object, n_classes: int,
                empty_ok: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        x = as_float_array("z", z, ndim=1)
        if not empty_ok:
            check_nonempty("z", x)
        y = as_int_array("labels", labels)
        check_length("labels", y, x.shape[0], "z")
        check_index("labels", y, n_classes, "classes")
        if distances is None:
            if self._needs_distances():
                raise FieldError("distances", f"distances is required: this "
                                 f"{type(self).__name__} has a range term")
            return x, y, None
        d = check_distances(distances, None)
        check_length("distances", d, x.shape[0], "z")
        return x, y, d

    #: Parametric methods: the length of a class's parameter vector, whose first entry (a
    #: temperature or a slope) must be > 0, and how a message names it; None: any length.
    _param_size: ClassVar[int | None] = None
    _param_text: ClassVar[str] = ""

    def _param_array(self, name: str, value: object) -> np.ndarray:
        arr = as_float_array(name, value, ndim=self._param_ndim)
        check_nonempty(name, arr)
        if self._param_size is not None and (arr.shape != (self._param_size,)
                                             or not arr[0] > 0):
            raise ValueError(f"{name} must be {self._param_text}, got {arr.tolist()}")
        return arr


def _rows_by_class(labels: np.ndarray, n_classes: int) -> list[np.ndarray]:
    """Row indices `[n_c]` of each class 0..C-1 (ascending), by one stable sort."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(n_classes + 1))
    return [order[bounds[k]:bounds[k + 1]] for k in range(n_classes)]


def check_shrink(shrink: Any) -> float:
    """`shrink` as a float >= 0; FieldError naming it otherwise."""
    if isinstance(shrink, bool) or not isinstance(shrink, int | float) \
            or not 0.0 <= float(shrink) < np.inf:
        raise FieldError("shrink", f"shrink must be a finite number >= 0, got {shrink!r}")
    return float(shrink)


def dict_key(data: dict[str, Any], key: str, what: str = "score calibrator") -> Any:
    """`data[key]` of the dict form of a `what`; ValueError naming a missing key."""
    if key not in data:
        raise ValueError(f"{what} dict lacks {key!r}")
    return data[key]


def unfitted(cls: type[_T], data: Any, what: str) -> _T:
    """A new, unfitted `cls` with the hyper-parameters of `data`, the dict form of a `what`
    (`data["hyper"]`, JSON lists back to tuples); ValueError when `data` is not a dict, lacks
    `hyper` or has one `cls` does not take. `from_dict` then sets the fitted attributes."""
    if not isinstance(data, dict):
        raise ValueError(f"a {what} must be a dict, got {type(data).__name__}")
    hyper = dict(dict_key(data, "hyper", what))
    try:
        return cls(**{name: tuple(v) if isinstance(v, list) else v for name, v in hyper.items()})
    except TypeError as exc:
        raise ValueError(f"hyper has a bad key: {exc}") from None
