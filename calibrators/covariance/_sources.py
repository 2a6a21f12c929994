"""Covariance sources: the spread of a query's box across the decoder layers (thesis 4.1.4),
and the one dispatch from a source name to the arrays it reads and the Σ it gives.

A DETR-style decoder refines each query's box layer by layer; the sample covariance of the
`L` per-layer boxes over the chosen dims is a cheap uncertainty estimate. `yaw` is an angle:
its deviations are wrapped to (-pi, pi] around the final layer's yaw before the covariance is
taken, so boxes at yaw ±pi are close, not 2·pi apart (this assumes the layers agree to within
pi, which holds for any sensible decoder).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from calibrators.core.checks import as_float_array
from calibrators.core.errors import FieldError, OptionError
from calibrators.core.vocab import (
    BOX_FIELDS,
    BOX_INDEX,
    COV_SOURCE_CHOICES,
    check_dims,
    wrap_angle,
)
from calibrators.covariance._hypotheses import hypotheses_covariance

if TYPE_CHECKING:
    from calibrators.data import Dump


def layer_spread(layer_boxes: np.ndarray, dims: Sequence[str] = ("x", "y")) -> np.ndarray:
    """Sample covariance (ddof=1) `[N, D, D]` of each query's box `[N, L, 9]` across layers.

    `dims` names the `D` box fields (`calibrators.core.vocab.BOX_FIELDS`), in the covariance's
    order.
    """
    idx = dim_indices(dims)
    boxes = as_float_array("layer_boxes", layer_boxes, ndim=3)
    if boxes.shape[2] != len(BOX_FIELDS):
        raise FieldError("layer_boxes", f"layer_boxes must have shape [N, L, 9], got "
                                        f"{boxes.shape}")
    n_layers = boxes.shape[1]
    if n_layers < 2:
        raise FieldError("layer_boxes", f"layer_boxes has {n_layers} decoder layer(s); the "
                                        "spread across layers needs L >= 2")
    values = boxes[:, :, idx]
    for j, name in enumerate(dims):
        if name == "yaw":
            values[:, :, j] = wrap_angle(values[:, :, j] - values[:, -1:, j])
    return sample_spread(values)


def sample_spread(values: np.ndarray) -> np.ndarray:
    """Sample covariance (ddof=1) `[N, D, D]` of each row's `L >= 2` values `[N, L, D]`:
    the spread across decoder layers, whatever the box parametrisation (`layer_spread` for the
    9-field boxes; `calibrators.boxes2d.edge_covariance` for image-plane box edges)."""
    centred = values - values.mean(axis=1, keepdims=True)
    return np.einsum("nli,nlj->nij", centred, centred) / (values.shape[1] - 1)


def dim_indices(dims: Sequence[str]) -> list[int]:
    """Column of each name of `dims` in a 9-field box; distinct known names are required."""
    return [BOX_INDEX[name] for name in check_dims(dims)]


#: The arrays each covariance source reads: keyword of `CalibrationProfile.calibrate` ->
#: the `Dump` attribute holding it (`auto` is resolved before, `none` reads nothing).
SOURCE_ARRAYS: dict[str, dict[str, str]] = {
    "given": {"covariances": "det_cov"},
    "layers": {"layer_boxes": "det_boxes"},
    "hypotheses": {"hyp_boxes": "det_hyp_boxes", "hyp_scores": "det_hyp_scores"},
    "none": {},
}


def source_inputs(source: str) -> str:
    """What a calibrate call carries for `source`, in words: `hyp_boxes with hyp_scores`,
    `neither` (none), ..."""
    return " with ".join(SOURCE_ARRAYS[source]) or "neither"


def takes_phrase(sources: Iterable[str]) -> str:
    """`; it takes covariances or layer_boxes` for several `sources` ("" for one)."""
    names = list(sources)
    return "" if len(names) < 2 else "; it takes " + " or ".join(map(source_inputs, names))


def source_covariance(source: str, dims: Sequence[str], *,
                      covariances: np.ndarray | None = None,
                      layer_boxes: np.ndarray | None = None,
                      hyp_boxes: np.ndarray | None = None,
                      hyp_scores: np.ndarray | None = None) -> np.ndarray | None:
    """`[N, D, D]` uncalibrated Σ over `dims` from covariance `source`: the given
    `covariances [N, D, D]`, the spread of `layer_boxes [N, L, 9]` (`layer_spread`), the
    spread of the box hypotheses `hyp_boxes [N, H, 9]` weighted by `hyp_scores [N, H]`
    (`hypotheses_covariance`), or None (`none`)."""
    if source == "given":
        return covariances
    if source == "layers":
        return layer_spread(layer_boxes, dims)
    if source == "hypotheses":
        return hypotheses_covariance(hyp_boxes, hyp_scores, dims)
    return None


def resolve_cov_source(dump: Dump, cov_source: str, dims: tuple[str, ...]) -> str:
    """The covariance source to use: `given`, `layers`, `hypotheses` or `none`.

    `auto` is `given` when the dump carries `det_cov` over exactly `dims`, else `layers` when
    it has at least two decoder layers, else `none`. `auto` never picks `hypotheses`: it is
    asked for by name (a dump fit with `auto` keeps the source it had before the hypothesis
    arrays existed, and `other_sources` fits a `hypotheses` stage beside it anyway). An
    explicit source the dump cannot provide raises an `OptionError` naming `cov_source`.
    """
    if cov_source not in COV_SOURCE_CHOICES:
        raise OptionError("cov_source", f"cov_source must be one of {list(COV_SOURCE_CHOICES)}, "
                                        f"got {cov_source!r}")
    if cov_source == "auto":
        if dump.det_cov is not None and dump.cov_dims == dims:
            return "given"
        return "layers" if dump.n_layers >= 2 else "none"
    if cov_source == "given":
        if dump.det_cov is None:
            raise OptionError("cov_source", "cov_source='given' but the dump has no det_cov")
        if dump.cov_dims != dims:
            raise OptionError("cov_source", f"cov_source='given' needs the dump's cov_dims "
                                            f"{list(dump.cov_dims)} to equal dims {list(dims)}")
    if cov_source == "layers" and dump.n_layers < 2:
        raise OptionError("cov_source", f"cov_source='layers' needs at least 2 decoder "
                                        f"layers, the dump has {dump.n_layers}")
    if cov_source == "hypotheses" and dump.n_hypotheses == 0:
        raise OptionError("cov_source", "cov_source='hypotheses' needs the dump's box "
                                        "hypotheses (det_hyp_boxes [N, H, 9] and "
                                        "det_hyp_scores [N, H], from group regression "
                                        "heads); the dump has none")
    return cov_source



def raw_covariances(dump: Dump, source: str, dims: tuple[str, ...]) -> np.ndarray | None:
    """`[N, D, D]` uncalibrated covariance of every detection from `source`, or None (`none`):
    `source_covariance` of the dump's `source_arrays`, as a served call computes it."""
    return source_covariance(source, dims, **source_arrays(dump, source))


def source_arrays(dump: Dump, source: str) -> dict[str, np.ndarray | None]:
    """The keyword arguments of `CalibrationProfile.calibrate` that carry covariance `source`
    from `dump`: `covariances [N, D, D]` (given), `layer_boxes [N, L, 9]` (layers),
    `hyp_boxes [N, H, 9]` and `hyp_scores [N, H]` (hypotheses), nothing (none); the table
    is `calibrators.covariance.SOURCE_ARRAYS`."""
    return {name: getattr(dump, attr) for name, attr in SOURCE_ARRAYS.get(source, {}).items()}
