"""The fit options every front end offers (`detcal fit`'s flags, `POST /v1/fit`'s form
fields): those of a 3-D fit (`calibrators.fit.FitOptions`) and of a 2-D fit on a COCO pair
(`calibrators.boxes2d.FitOptions2D`), one flag or field per name.

A name both fits take (`holdout`, `seed`, `calibration`, `score_method`, `min_samples`,
`min_group`) is one option with one default; its allowed values are both fits' (each fit's
own check then refuses the other's: `score_method=position` is a 2-D method). An option of
one kind of fit given to the other is refused, named (`OptionError`), never ignored.
Imports the library only (the CLI works without the service extras).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from calibrators.boxes2d import FitOptions2D
from calibrators.core.errors import OptionError
from calibrators.fit import FitOptions, OptionSpec

__all__ = ["fit_option_specs", "options_of"]


def fit_option_specs() -> tuple[OptionSpec, ...]:
    """One `OptionSpec` per option name of either fit: the 3-D options in their order, then
    the 2-D-only ones; a shared name's choices are both fits' and its help says both."""
    specs = {s.name: s for s in FitOptions.describe()}
    for s in FitOptions2D.describe():
        own = specs.get(s.name)
        if own is None:
            specs[s.name] = OptionSpec(s.name, s.type, s.default, s.choices, s.nullable,
                                       f"COCO fits only: {s.help}")
            continue
        if own.default != s.default or own.type is not s.type:   # one name, one default
            raise TypeError(f"fit option {s.name!r}: the 3-D and 2-D fits give it different "
                            f"defaults or types")
        choices = None if own.choices is None else tuple(
            dict.fromkeys((*own.choices, *(s.choices or ()))))
        text = own.help if own.help == s.help else f"{own.help}; COCO fits: {s.help}"
        specs[s.name] = OptionSpec(s.name, own.type, own.default, choices, own.nullable, text)
    return tuple(specs.values())


def options_of(values: Mapping[str, Any], given: set[str], coco: bool
               ) -> FitOptions | FitOptions2D:
    """The options of a 3-D fit (`coco` False) or of a 2-D fit on a COCO pair from the front
    end's `values` (every name of `fit_option_specs`, defaults included); `given` names the
    options the user set. OptionError naming an option the fit does not take, or a bad value."""
    kind, other = (FitOptions2D, FitOptions) if coco else (FitOptions, FitOptions2D)
    own = {s.name for s in kind.describe()}
    foreign = sorted((given & {s.name for s in other.describe()}) - own)
    if foreign:
        what = "a 3-D fit" if coco else "a COCO (2-D) fit"
        raise OptionError(foreign[0], f"{foreign[0]} is an option of {what}; this fit is "
                                      f"{'a COCO (2-D) fit' if coco else 'a 3-D fit'}")
    return kind.from_dict({k: v for k, v in values.items() if k in own})
