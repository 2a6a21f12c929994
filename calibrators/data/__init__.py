"""The validation dump: `Dump` (detections of every decoder layer, ground truth, frames; the
data contract of docs/formats.md), frame selection (`split_frames` holds out frames by a
seeded hash of their token, `canonical_order` makes a fit free of input order) and the
synthetic dumps of the tests and examples (`synthetic_dump`).
"""

from calibrators.data._dump import Dump, concat_frames
from calibrators.data._frames import (
    canonical_order,
    held_out_frames,
    select_detections,
    split_frames,
)
from calibrators.data._synthetic import CLASSES10, DEFAULT_DEPTH_K, synthetic_dump

__all__ = ["CLASSES10", "DEFAULT_DEPTH_K", "Dump", "canonical_order", "concat_frames",
           "held_out_frames", "select_detections", "split_frames", "synthetic_dump"]
