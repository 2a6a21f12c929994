"""Input validation shared by the library: every error names the argument and the reason."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.core.errors import FieldError, NotFittedError


def as_float_array(name: str, value: object, ndim: int | None = None) -> np.ndarray:
    """Return `value` as a finite float64 array, or raise a ValueError naming `name`.

    `ndim`, when given, is the required number of dimensions.
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise FieldError(name, f"{name} must be numeric: {exc}") from None
    if ndim is not None and arr.ndim != ndim:
        raise FieldError(name, f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    check_finite(name, arr)
    return arr


def check_finite(name: str, arr: np.ndarray) -> None:
    """Raise a ValueError naming the first non-finite entry of `arr`."""
    if arr.dtype.kind not in "fc":
        return
    bad = ~np.isfinite(arr)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        value = arr[where]
        kind = "NaN" if np.isnan(value) else "Inf"
        loc = where[0] if len(where) == 1 else list(where)
        raise FieldError(name, f"{name} has {kind} at index {loc}", row=where[0])


def as_int_array(name: str, value: object, ndim: int = 1) -> np.ndarray:
    """Return `value` as an int64 array of `ndim` dimensions; floats must be whole numbers."""
    arr = np.asarray(value)
    if arr.ndim != ndim:
        raise FieldError(name, f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    if arr.size and arr.dtype.kind == "f":
        check_finite(name, arr)
        if not np.all(arr == np.round(arr)):
            raise FieldError(name, f"{name} must hold integers")
    elif arr.size and arr.dtype.kind not in "iub":
        raise FieldError(name, f"{name} must hold integers, got dtype {arr.dtype}")
    return arr.astype(np.int64)


def check_length(name: str, arr: np.ndarray, n: int, other: str) -> None:
    """Raise unless `arr` has `n` rows, the row count of `other`."""
    if arr.shape[0] != n:
        raise FieldError(name, f"{name} has {arr.shape[0]} rows but {other} has {n}")


def check_index(name: str, arr: np.ndarray, upper: int, what: str) -> None:
    """Raise unless every entry of `arr` is in [0, upper)."""
    if arr.size == 0:
        return
    bad = (arr < 0) | (arr >= upper)
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError(name, f"{name}[{i}] = {int(arr[i])} is out of range for {upper} {what}",
                         row=i)


def check_probabilities(name: str, arr: np.ndarray) -> None:
    """Raise unless every entry of `arr` is in [0, 1]."""
    bad = (arr < 0.0) | (arr > 1.0)
    if bad.any():
        i = int(np.argmax(bad.reshape(-1)))
        value = arr.reshape(-1)[i]
        raise FieldError(name, f"{name} must hold probabilities in [0, 1]; entry {i} is {value}",
                         row=int(np.unravel_index(i, arr.shape)[0]))


def covariance_tolerance(magnitude: np.ndarray, dim: int,
                         dtype: np.dtype | type = np.float64) -> np.ndarray:
    """Rounding allowance of the symmetry and PSD tests, per matrix: `8·D·ε·magnitude`.

    `magnitude` `[N]` is each matrix's largest absolute entry (within a factor D of its largest
    absolute eigenvalue), `ε` the machine epsilon of `dtype` but never finer than float32's: a
    float64 array (or JSON) usually carries a float32 detector's numbers, whose rounding moves
    an eigenvalue of a PSD matrix by up to about `D·ε·magnitude` below 0. The allowance scales
    with the matrix, so no absolute floor: a 1e200 covariance and a 1e-12 one are judged alike.
    """
    kind = np.dtype(dtype)
    eps = np.finfo(np.float32).eps
    if kind.kind == "f":
        eps = max(eps, np.finfo(kind).eps)
    return np.asarray(magnitude, dtype=np.float64) * (8.0 * max(int(dim), 1) * float(eps))


def check_covariances(name: str, cov: np.ndarray, n: int | None = None, dim: int | None = None,
                      dtype: np.dtype | type | None = None) -> None:
    """Raise unless `cov` is `[N, D, D]`, symmetric and positive semi-definite.

    Both tests allow rounding relative to each matrix (`covariance_tolerance`, with `dtype`
    the precision the numbers were computed in, default `cov.dtype`): `Σ - Σᵀ` and the
    smallest eigenvalue may be off by `8·D·ε·max|Σ|`; an indefinite matrix such as
    [[1, 2], [2, 1]] (smallest eigenvalue -1) is refused at any scale.
    """
    if cov.ndim != 3 or cov.shape[1] != cov.shape[2]:
        raise FieldError(name, f"{name} must have shape [N, D, D], got {cov.shape}")
    if n is not None and cov.shape[0] != n:
        raise FieldError(name, f"{name} has {cov.shape[0]} matrices but {n} were expected")
    if dim is not None and cov.shape[1] != dim:
        raise FieldError(name, f"{name} must be {dim}x{dim}, got {cov.shape[1]}x{cov.shape[2]}")
    check_finite(name, cov)
    if cov.shape[0] == 0 or cov.shape[1] == 0:
        return
    tol = covariance_tolerance(np.abs(cov).max(axis=(1, 2)), cov.shape[1],
                               cov.dtype if dtype is None else dtype)
    asym = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2)) > tol
    if asym.any():
        i = int(np.argmax(asym))
        raise FieldError(name, f"{name}[{i}] is not symmetric", row=i)
    eig_min = _smallest_eigenvalue(cov)
    bad = eig_min < -tol
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError(name, f"{name}[{i}] is not positive semi-definite (smallest "
                               f"eigenvalue {eig_min[i]:.3g}, allowed rounding "
                               f"{-tol[i]:.3g})", row=i)


def _smallest_eigenvalue(cov: np.ndarray) -> np.ndarray:
    """λ_min `[N]` of symmetric `[N, D, D]`: closed form for D = 2 ((a + c)/2 - hypot((a - c)/2,
    b), the common case, ~10x faster than LAPACK on small batches), else `eigvalsh`."""
    if cov.shape[1] == 2:
        a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
        return 0.5 * (a + c) - np.hypot(0.5 * (a - c), b)
    if cov.shape[1] == 1:
        return cov[:, 0, 0]
    return np.linalg.eigvalsh(cov)[:, 0]


def check_choice(name: str, value: str, choices: Sequence[str]) -> None:
    """Raise unless `value` is one of `choices`."""
    if value not in choices:
        raise FieldError(name, f"{name} must be one of {list(choices)}, got {value!r}")


def check_positive(name: str, value: object) -> float:
    """`value` as a float, or a FieldError unless it is a finite number > 0."""
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise FieldError(name, f"{name} must be a finite number > 0, got {value!r}") from None
    if not np.isfinite(x) or x <= 0:
        raise FieldError(name, f"{name} must be a finite number > 0, got {value}")
    return x


def check_min_samples(value: int) -> int:
    """`value` as an int >= 1 (an estimator's `min_samples`), or a ValueError."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"min_samples must be an integer >= 1, got {value!r}")
    return int(value)


def check_bounds(bounds: tuple[float, float], *, zero_low: bool = False
                 ) -> tuple[float, float]:
    """An estimator's search `bounds` as floats `(low, high)`: finite, `0 < low < high`
    (`0 <= low` with `zero_low`), or a ValueError."""
    try:
        low, high = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise ValueError(f"bounds must be a pair of numbers, got {bounds!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and (0 <= low if zero_low else 0 < low)
            and low < high):
        raise ValueError(f"bounds must satisfy 0 {'<=' if zero_low else '<'} low < high "
                         f"(finite), got {bounds!r}")
    return low, high


def check_distances(distances: np.ndarray, n: int | None) -> np.ndarray:
    """`distances [N]` as float64, each >= 0 (N = `n` residuals unless None), or a ValueError."""
    d = as_float_array("distances", distances, ndim=1)
    if n is not None:
        check_length("distances", d, n, "residuals")
    negative = d < 0
    if negative.any():
        i = int(np.argmax(negative))
        raise ValueError(f"distances[{i}] = {d[i]} is negative")
    return d


def class_codes(classes: np.ndarray, n: int) -> tuple[list, np.ndarray]:
    """Distinct class labels (as Python scalars, sorted) and the code `[N]` of each entry."""
    arr = np.asarray(classes)
    if arr.ndim != 1:
        raise ValueError(f"classes must have 1 dimension, got shape {arr.shape}")
    check_length("classes", arr, n, "distances")
    if n == 0:
        return [], np.zeros(0, dtype=np.int64)
    if arr.dtype.kind in "iu":
        low, high = int(arr.min()), int(arr.max())
        if high - low <= 4 * n:  # small integer labels: a counting pass, no sort
            shifted = arr - low if low else arr
            present = np.bincount(shifted, minlength=high - low + 1) > 0
            keys = (np.flatnonzero(present) + low).tolist()
            if not low and present.all():  # labels 0 .. C - 1: each its own code
                return keys, shifted.astype(np.int64)
            return keys, (np.cumsum(present) - 1)[shifted]
    try:
        keys, codes = np.unique(arr, return_inverse=True)
    except TypeError:
        raise ValueError("classes must be labels of one comparable type (all ints or all strs)"
                         ) from None
    return keys.tolist(), codes.reshape(-1).astype(np.int64)


def check_fitted(estimator: object, attribute: str) -> None:
    """Raise NotFittedError unless fit has set `attribute` (trailing underscore) on `estimator`."""
    if not hasattr(estimator, attribute):
        name = type(estimator).__name__
        raise NotFittedError(f"this {name} is not fitted yet: call fit(...) before using it")
