"""One check shared by the Arrow tests: an Arrow answer carries the JSON answer's floats."""

from __future__ import annotations

import numpy as np
import pyarrow as pa


def assert_same_floats(table: pa.Table, dets: list[dict], levels: tuple[str, ...] = ("0.5", "0.9")
                       ) -> None:
    """Scores, raw scores, distances, covariances and the ellipses at `levels` of the Arrow
    `table` equal, bit for bit, those of the JSON detections `dets` (same order)."""
    for column in ("score", "score_raw", "distance"):
        assert table[column].to_pylist() == [d[column] for d in dets], column
    assert [np.ravel(c).tolist() for c in table["covariance"].to_pylist()] == [
        np.ravel(d["covariance"]).tolist() for d in dets]
    for level in levels:
        arrow = table[f"ellipse_{level}"].to_pylist()
        assert [(e["semi_major"], e["semi_minor"], e["angle"]) for e in arrow] == [
            (d["ellipses"][level]["semi_major"], d["ellipses"][level]["semi_minor"],
             d["ellipses"][level]["angle"]) for d in dets]
