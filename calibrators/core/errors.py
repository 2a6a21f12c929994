"""Exceptions of the calibration library."""

from __future__ import annotations


class NotFittedError(ValueError, AttributeError):
    """An estimator was used before `fit` (as scikit-learn's NotFittedError, also a ValueError)."""




class FieldError(ValueError):
    """Bad input to a library call: `field` names the argument (e.g. `covariances`) and `row`
    the offending row of it when one row is at fault (else None). Front ends map both to their
    own field paths (a 422's `loc`, a CLI message) without parsing the text."""

    def __init__(self, field: str, message: str, row: int | None = None) -> None:
        super().__init__(message)
        self.field = field
        self.row = row


class OptionError(FieldError):
    """A fit option has a bad value; `field` is the option's name."""
