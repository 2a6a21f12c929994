"""What cannot be exported is refused with an `ExportError` naming it; nothing is written."""

from __future__ import annotations

import dataclasses

import pytest

from calibrators import CalibrationProfile, fit_profile
from calibrators.data import synthetic_dump
from detectors.export import ExportError, build_graph, export_profile
from detectors.export import graph as graph_module
from tests.detectors.export_cases import V1_PROFILE


@pytest.fixture(scope="module")
def v1() -> CalibrationProfile:
    return CalibrationProfile.from_json(V1_PROFILE.read_text())


@pytest.fixture(scope="module")
def conformal() -> CalibrationProfile:
    dump = synthetic_dump(n_frames=30, seed=21)
    return fit_profile(dump, region_method="conformal", min_group=20, cov_source="given")


@pytest.fixture(scope="module")
def modulated() -> CalibrationProfile:
    dump = synthetic_dump(n_frames=20, seed=22)
    return fit_profile(dump, modulation=True, score_method="temperature", cov_source="none")


def test_a_source_the_profile_does_not_serve(v1):
    with pytest.raises(ExportError, match=r"cov_source 'layers' is not served.*\['given'\]"):
        build_graph(v1, cov_source="layers")


def test_modulation_needs_layer_logits(modulated):
    with pytest.raises(ExportError, match="modulation, which needs layer_logits"):
        build_graph(modulated, layer_logits=False)
    assert build_graph(modulated).input_names[0] == "layer_logits"


def test_a_level_a_conformal_group_cannot_bound_is_unbounded_as_in_the_library(
        conformal, tmp_path):
    import numpy as np
    import onnxruntime as ort

    dump = synthetic_dump(n_frames=4, seed=5)
    n = min(40, dump.n_detections)
    values = {"logits": dump.det_logits[:n, -1], "boxes": dump.det_boxes[:n, -1],
              "ego_xy": np.zeros((n, 2)), "covariances_raw": dump.det_cov[:n]}
    lib = conformal.calibrate(logits=values["logits"], boxes=values["boxes"],
                              ego_xy=values["ego_xy"], covariances=values["covariances_raw"],
                              levels=[0.5, 0.9999])
    assert np.isinf(lib.regions[0.9999].semi_major).all()
    export_profile(conformal, tmp_path / "g.onnx", levels=(0.5, 0.9999))
    session = ort.InferenceSession(str(tmp_path / "g.onnx"),
                                   providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    out = dict(zip([o.name for o in session.get_outputs()],
                   session.run(None, {k: values[k] for k in names}), strict=True))
    np.testing.assert_array_equal(out["semi_major"][:, 1], lib.regions[0.9999].semi_major)
    np.testing.assert_array_equal(out["semi_minor"][:, 1], lib.regions[0.9999].semi_minor)
    np.testing.assert_allclose(out["semi_major"][:, 0], lib.regions[0.5].semi_major,
                               rtol=1e-9, atol=0)


@pytest.mark.parametrize("levels, text", [((1.5,), r"levels\[0\] = 1.5"), ((), "non-empty"),
                                          ((0.5, 0.5), "repeats")])
def test_bad_levels(v1, levels, text):
    with pytest.raises(ExportError, match=text):
        build_graph(v1, levels=levels)


def test_bad_format_dtype_and_profile(v1, tmp_path):
    with pytest.raises(ExportError, match="format must be one of"):
        export_profile(v1, tmp_path / "g", "tflite")
    with pytest.raises(ExportError, match="input_dtype must be one of"):
        export_profile(v1, tmp_path / "g", "onnx", input_dtype="float16")
    with pytest.raises(ExportError, match="must be a CalibrationProfile"):
        build_graph(V1_PROFILE.read_text())  # type: ignore[arg-type]
    assert not list(tmp_path.iterdir())


def test_a_stage_method_without_a_graph_is_named(v1, monkeypatch):
    """A method added to the library but not to the exporter is refused, never dropped."""
    monkeypatch.setattr(graph_module, "score_stage", lambda value: ("beta", object()))
    with pytest.raises(ExportError, match="score_calibration.method 'beta' cannot be exported"):
        build_graph(v1)
    monkeypatch.undo()

    real = graph_module._source
    for change, text in (({"cov_method": "quantile"}, "covariance_scaling.method 'quantile'"),
                         ({"region_method": "bootstrap"}, "regions.method 'bootstrap'")):
        monkeypatch.setattr(graph_module, "_source",
                            lambda p, s, change=change: dataclasses.replace(real(p, s), **change))
        with pytest.raises(ExportError, match=text):
            build_graph(v1)


def test_no_regions_without_x_and_y():
    """cov_dims without x or y: the library serves no ellipses, nor does the graph."""
    dump = synthetic_dump(n_frames=20, seed=23)
    profile = fit_profile(dump, dims=("x", "z"), cov_source="layers", score_method="platt",
                          region_method="gaussian")
    graph = build_graph(profile, levels=(0.5, 0.9))
    assert graph.output_names == ["labels", "scores", "scores_raw", "distances", "covariances"]
