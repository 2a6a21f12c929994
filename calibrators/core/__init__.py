"""The library's core: what every other package uses and nothing here imports from them.

- `vocab`: box fields, covariance sources, score modes and methods; angle wrapping.
- `defaults`: the served ellipse level, the default region levels, the matching distance.
- `checks`: argument checks that raise `FieldError` naming the argument.
- `errors`: `FieldError`, `OptionError`, `NotFittedError`.
- `json_safe`: the one conversion of numpy values to strict JSON.
- `bins`: binning of confidences and outcomes shared by metrics and calibrators, and the
  `to_dict` mixin of metric results.
- `selection`: `choose_lowest_nll`, how every `auto` option of a fit chooses among its
  candidates.

Import the modules themselves (`from calibrators.core.vocab import BOX_FIELDS`).
"""
