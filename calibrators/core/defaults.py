"""The library's defaults, defined once: every signature, schema and command reads them here.

`ELLIPSE_CONFIDENCE` is the coverage of the one ellipse each calibrated detection carries,
`DEFAULT_LEVELS` the levels of the served regions when a request names none, and
`MATCH_THRESHOLD` the nuScenes matching distance (m) of a true positive.
"""

from __future__ import annotations

#: Coverage level of the `ellipse` each calibrated detection carries.
ELLIPSE_CONFIDENCE: float = 0.95
#: Coverage levels of the served regions (`ellipses`) when a request or command names none.
DEFAULT_LEVELS: tuple[float, ...] = (0.95,)
#: nuScenes matching: a detection is a true positive iff its centre lies within this
#: distance (m, BEV) of an unmatched ground truth of its class.
MATCH_THRESHOLD: float = 2.0
