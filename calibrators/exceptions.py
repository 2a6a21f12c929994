"""Exceptions of the calibration library."""

from __future__ import annotations


class NotFittedError(ValueError, AttributeError):
    """An estimator was used before `fit` (as scikit-learn's NotFittedError, also a ValueError)."""


def check_fitted(estimator: object, attribute: str) -> None:
    """Raise NotFittedError unless fit has set `attribute` (trailing underscore) on `estimator`."""
    if not hasattr(estimator, attribute):
        name = type(estimator).__name__
        raise NotFittedError(f"this {name} is not fitted yet: call fit(...) before using it")
