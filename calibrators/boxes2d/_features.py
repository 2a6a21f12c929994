"""Box position features for detection calibration (netcal's `detection=True` inputs): the
box centre and size relative to the image,

    cx = (x + w/2) / W,  cy = (y + h/2) / H,  w / W,  h / H

for a COCO box `x, y, w, h` in an image of `W x H` pixels (each in [0, 1] for a box inside
its image). Used by the D-ECE bins (`detection_ece_2d`) and the position-dependent score
calibrator (`PositionCalibrator`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.boxes2d._boxes import check_bbox
from calibrators.core.checks import as_float_array, check_length
from calibrators.core.errors import FieldError

__all__ = ["BOX_FEATURES", "box_features", "check_features"]

#: The position features, in their default order.
BOX_FEATURES: tuple[str, ...] = ("cx", "cy", "w", "h")


def check_features(names: Sequence[str], name: str = "features") -> tuple[str, ...]:
    """`names` as a tuple of distinct entries of `BOX_FEATURES` (at least one), or a
    FieldError naming `name`."""
    if isinstance(names, str):
        names = [names]
    try:
        out = tuple(names)
    except TypeError:
        raise FieldError(name, f"{name} must be a list of {list(BOX_FEATURES)}, got "
                               f"{names!r}") from None
    bad = [f for f in out if f not in BOX_FEATURES]
    if not out or bad or len(set(out)) != len(out):
        raise FieldError(name, f"{name} must list distinct names among {list(BOX_FEATURES)} "
                               f"(at least one), got {list(out)}")
    return out


def box_features(bbox: np.ndarray, image_size: np.ndarray,
                 features: Sequence[str] = BOX_FEATURES) -> np.ndarray:
    """`[N, F]` normalised features (module docstring) of COCO boxes `bbox [N, 4]` in images
    of `image_size [N, 2]` (width W, height H in pixels, > 0), F = the named `features`."""
    names = check_features(features)
    box = check_bbox("bbox", bbox, None)
    size = as_float_array("image_size", image_size, ndim=2)
    if size.shape[1:] != (2,):
        raise FieldError("image_size", f"image_size must have shape [N, 2] (width, height), "
                                       f"got {size.shape}")
    check_length("image_size", size, len(box), "bbox")
    bad = ~(size > 0).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError("image_size", f"image_size[{i}] must be > 0, got {size[i].tolist()}",
                         row=i)
    width, height = size[:, 0], size[:, 1]
    columns = {"cx": (box[:, 0] + 0.5 * box[:, 2]) / width,
               "cy": (box[:, 1] + 0.5 * box[:, 3]) / height,
               "w": box[:, 2] / width, "h": box[:, 3] / height}
    return np.stack([columns[f] for f in names], axis=1).reshape(len(box), len(names))
