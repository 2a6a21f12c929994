"""`detcal export --labels`: a graph with a `labels [N]` input scores the class each detection
asserts (top-K (query, class) decoding: one query, several classes), as the library does with
`labels` beside the logits, in torch, TorchScript and ONNX; without the input, the arg-max."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from calibrators import Dump, fit_profile
from calibrators.data import synthetic_dump
from detectors.export import build_graph, export_profile
from tests.detectors.export_cases import LEVELS, TOLERANCE, differences


def _top2(dump: Dump) -> Dump:
    """Every detection twice: its arg-max class and its second class."""
    second = np.argsort(-dump.det_logits[:, -1, :len(dump.classes)], axis=1)[:, 1]
    rows = np.repeat(np.arange(dump.n_detections), 2)
    return Dump(classes=dump.classes, score_mode=dump.score_mode, frame_ids=dump.frame_ids,
                det_frame=dump.det_frame[rows], det_logits=dump.det_logits[rows],
                det_boxes=dump.det_boxes[rows], det_cov=dump.det_cov[rows],
                gt_frame=dump.gt_frame, gt_labels=dump.gt_labels, gt_boxes=dump.gt_boxes,
                det_hyp_boxes=None if dump.det_hyp_boxes is None else dump.det_hyp_boxes[rows],
                det_hyp_scores=None if dump.det_hyp_scores is None
                else dump.det_hyp_scores[rows],
                det_label=np.stack([dump.det_labels, second], axis=1).reshape(-1))


CASES = {
    "sigmoid-platt-given": (dict(seed=21), dict(score_method="platt", cov_source="given")),
    "softmax-temperature-given": (dict(seed=22, score_mode="softmax", temperature=1.5),
                                  dict(score_method="temperature", cov_source="given")),
    "sigmoid-hypotheses": (dict(seed=23, n_hypotheses=4),
                           dict(cov_source="hypotheses", other_sources=False)),
}


@pytest.fixture(scope="module", params=list(CASES))
def case(request):
    data, options = CASES[request.param]
    dump = _top2(synthetic_dump(n_frames=30, **data))
    return request.param, dump, fit_profile(dump, **options)


def _inputs(names: list[str], dump: Dump) -> list[np.ndarray]:
    values = {"logits": dump.det_logits[:, -1], "labels": dump.det_labels,
              "boxes": dump.final_boxes, "ego_xy": dump.ego_xy(dump.det_frame),
              "covariances_raw": dump.det_cov, "hyp_boxes": dump.det_hyp_boxes,
              "hyp_scores": dump.det_hyp_scores}
    return [np.ascontiguousarray(values[n]) for n in names]


def _library(profile, dump: Dump, labels: bool):
    source = profile.cov_source
    return profile.calibrate(
        logits=dump.det_logits[:, -1], labels=dump.det_labels if labels else None,
        boxes=dump.final_boxes, ego_xy=dump.ego_xy(dump.det_frame),
        covariances=dump.det_cov if source == "given" else None,
        hyp_boxes=dump.det_hyp_boxes if source == "hypotheses" else None,
        hyp_scores=dump.det_hyp_scores if source == "hypotheses" else None, levels=LEVELS)


def _check(out: dict, lib) -> None:
    worst = {k: gap for k, (gap, _) in differences(out, lib).items() if gap > TOLERANCE}
    assert not worst, worst


@pytest.mark.filterwarnings("ignore:`torch.jit.load` is deprecated")
def test_the_labels_input_scores_the_given_class(case, tmp_path):
    name, dump, profile = case
    graph = build_graph(profile, levels=LEVELS, labels=True).eval()
    assert graph.input_names[:2] == ["logits", "labels"]
    assert json.loads(graph.metadata)["labels_input"] is True
    tensors = [torch.from_numpy(a) for a in _inputs(graph.input_names, dump)]
    lib = _library(profile, dump, labels=True)
    assert not np.array_equal(lib.labels, _library(profile, dump, labels=False).labels)
    _check({k: v.numpy() for k, v in graph(*tensors).items()}, lib)

    export_profile(profile, tmp_path / "g.pt", "torchscript", levels=LEVELS, labels=True)
    scripted = torch.jit.load(str(tmp_path / "g.pt"))
    _check({k: v.numpy() for k, v in scripted(*tensors).items()}, lib)

    # without the input the graph is what it was: the arg-max
    plain = build_graph(profile, levels=LEVELS).eval()
    out = plain(*[torch.from_numpy(a) for a in _inputs(plain.input_names, dump)])
    _check({k: v.numpy() for k, v in out.items()}, _library(profile, dump, labels=False))


def test_onnx_takes_int64_labels(case, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    name, dump, profile = case
    meta = export_profile(profile, tmp_path / "g.onnx", "onnx", levels=LEVELS, labels=True)
    session = ort.InferenceSession(str(tmp_path / "g.onnx"),
                                   providers=["CPUExecutionProvider"])
    types = {i.name: i.type for i in session.get_inputs()}
    assert types["labels"] == "tensor(int64)" and meta["inputs"][1] == "labels"
    values = _inputs(meta["inputs"], dump)
    out = session.run(None, dict(zip(meta["inputs"], values, strict=True)))
    names = [o.name for o in session.get_outputs()]
    _check(dict(zip(names, out, strict=True)), _library(profile, dump, labels=True))
