"""`detcal export` keeps each detection's identity (issue 27): the exported graph, run on a
dump's detections in any order (moved within and across frames, frames reordered, duplicate
boxes, empty frames), gives every detection the values it gives in the dump's own order, and
the library serves."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from app.cli.main import main
from calibrators import apply_profile
from calibrators.profile import CalibrationProfile
from tests.identity_cases import CASES, awkward, shuffled

ort = pytest.importorskip("onnxruntime")
pytest.importorskip("torch")


@pytest.fixture(scope="module")
def graph(tmp_path_factory, profile_json_given):
    """(an ONNX session of the conftest profile at levels 0.5 / 0.9, the profile)."""
    folder = tmp_path_factory.mktemp("export")
    (folder / "p.json").write_text(profile_json_given)
    out = folder / "calibration.onnx"
    assert main(["export", str(folder / "p.json"), "--out", str(out), "--levels", "0.5",
                 "0.9"]) == 0
    return (ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]),
            CalibrationProfile.from_json(profile_json_given))


def _run(session, dump) -> dict[str, np.ndarray]:
    names = [o.name for o in session.get_outputs()]
    got = session.run(names, {"logits": dump.det_logits[:, -1], "boxes": dump.final_boxes,
                              "ego_xy": dump.ego_xy(dump.det_frame),
                              "covariances_raw": dump.det_cov})
    return dict(zip(names, got, strict=True))


@settings(max_examples=6, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=CASES)
def test_the_exported_graph_serves_every_detection_the_same_in_any_order(graph, dump_given,
                                                                          case):
    session, profile = graph
    dump = awkward(dump_given, case)
    moved, perm = shuffled(dump, case["seed"])
    a, b = _run(session, dump), _run(session, moved)
    # onnxruntime's vectorised kernels take a row's lanes by its position in the batch, so a
    # moved row may round differently in its last bit (one ulp seen): each detection's values
    # must agree to 1e-12 relative, far below anything served, not bit for bit.
    for name in a:
        np.testing.assert_allclose(b[name], a[name][perm], rtol=1e-12, atol=0, err_msg=name)
    ref = apply_profile(moved, profile)
    np.testing.assert_allclose(b["scores"], ref.scores, rtol=1e-9)
    np.testing.assert_allclose(b["covariances"], ref.covariances, rtol=1e-9, atol=1e-12)
