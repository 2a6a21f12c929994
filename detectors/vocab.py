"""The detectors' vocabulary, defined once: sensors, splits, the detector's own covariance
sources, ground-truth filters, decodings and dump formats.

Plain tuples with no imports, so that the `detcal` CLI can offer them as choices without
loading torch or the simulator. The simulator (`detectors.sim`), the registry, the dump
writer, `detcal show` and the report import these names instead of spelling them again.
The calibration library's words (box fields, the *profile's* covariance sources, score
modes, angle wrapping) live in `calibrators.core.vocab`.
"""

from __future__ import annotations

#: The simulated sensors; each has one bundled detector (`detectors.registry`).
SENSORS: tuple[str, ...] = ("lidar", "radar1", "radar5", "camera")
#: The scene-seed splits (`detectors.sim.SPLITS` holds their seed ranges). `holdout` is never
#: trained on, fit on or chosen by: held-out measurements of served calibration draw from it.
SPLIT_NAMES: tuple[str, ...] = ("train", "val", "test", "holdout")
#: Where a bundled detector's own (x, y) box covariance comes from: the sample covariance of
#: a query's box across decoder layers (`layers`, thesis) or the final layer's attention
#: spread plus the variance of a uniform position in one token cell (`attention`, seed 000).
#: Not `calibrators.core.vocab.COV_SOURCES`, which says where a *profile* takes its Σ from.
DETECTOR_COV_SOURCES: tuple[str, ...] = ("layers", "attention")
#: What a dump's `det_cov` holds (`detcal dump --cov-source`): a detector source, or nothing.
DUMP_COV_SOURCES: tuple[str, ...] = (*DETECTOR_COV_SOURCES, "none")
#: Which ground-truth boxes a dump keeps: those with a lidar or radar point (nuScenes rule),
#: those with a point of the dumped sensor, or all.
GT_FILTERS: tuple[str, ...] = ("lidar_radar", "sensor", "none")
#: File formats `detcal dump` writes: validation dump v1 NPZ, or nuScenes results + GT JSON.
DUMP_FORMATS: tuple[str, ...] = ("npz", "nuscenes")
#: How detections are read off a detector's queries (`detectors.infer`; the first is the
#: default): the best (query, class) pairs after class-wise circle NMS; the best pairs, a
#: query may give several classes (DETR3D's and PETR's NMS-free coder); or one detection per
#: query, its arg-max class.
DECODINGS: tuple[str, ...] = ("topk_nms", "topk", "query")
