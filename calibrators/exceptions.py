"""Exceptions of the calibration library."""

from __future__ import annotations


class NotFittedError(ValueError, AttributeError):
    """An estimator was used before `fit` (as scikit-learn's NotFittedError, also a ValueError)."""


def check_fitted(estimator: object, attribute: str) -> None:
    """Raise NotFittedError unless fit has set `attribute` (trailing underscore) on `estimator`."""
    if not hasattr(estimator, attribute):
        name = type(estimator).__name__
        raise NotFittedError(f"this {name} is not fitted yet: call fit(...) before using it")


class FieldError(ValueError):
    """Bad input to a library call: `field` names the argument (e.g. `covariances`) and `row`
    the offending row of it when one row is at fault (else None). Front ends map both to their
    own field paths (a 422's `loc`, a CLI message) without parsing the text."""

    def __init__(self, field: str, message: str, row: int | None = None) -> None:
        super().__init__(message)
        self.field = field
        self.row = row
