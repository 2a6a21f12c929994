"""Reading detections off the queries: "topk" (the best (query, class) pairs, DETR3D's and
PETR's NMS-free coder), "topk_nms" (the same after class-wise circle NMS, the default) and
"query" (one detection per query, its arg-max class)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from calibrators.io import load_dump
from detectors.dumpwriter import build_dump, write_dump
from detectors.infer import postprocess
from detectors.model import Detector

SEEDS = (100000, 100001)


def _outputs(logits: torch.Tensor) -> dict[str, torch.Tensor]:
    """A detector output dict around final logits `[Q, C]` (2 layers, batch 1)."""
    q, _ = logits.shape
    boxes = torch.arange(q, dtype=torch.float32)[:, None].expand(q, 9)
    return {"pred_logits": torch.stack([logits - 1.0, logits])[:, None],
            "pred_boxes": torch.stack([boxes, boxes])[:, None],
            "attention": torch.full((2, 1, q, 4), 0.25)}


def test_topk_reads_pairs_in_score_order_and_repeats_queries():
    p = torch.tensor([[0.6, 0.4, 0.01], [0.05, 0.02, 0.9], [0.3, 0.01, 0.01]])
    (det,) = postprocess(_outputs(torch.logit(p)), max_detections=4, decode="topk")
    assert det.query_index.tolist() == [1, 0, 0, 2]
    assert det.labels.tolist() == [2, 0, 1, 0]
    torch.testing.assert_close(det.scores, torch.tensor([0.9, 0.6, 0.4, 0.3]))
    # each detection carries its query's outputs
    assert det.boxes[:, 0].tolist() == [1.0, 0.0, 0.0, 2.0]
    (one,) = postprocess(_outputs(torch.logit(p)), max_detections=4, decode="query")
    assert one.query_index.tolist() == [1, 0, 2] and one.labels.tolist() == [2, 0, 0]
    with pytest.raises(ValueError, match="decode"):
        postprocess(_outputs(torch.logit(p)), decode="nms")


def test_dumps_carry_the_decoded_labels(tmp_path, tiny_config):
    torch.manual_seed(0)
    model = Detector(tiny_config("radar5")).eval()
    topk = build_dump(model, SEEDS, max_detections=30, gt_filter="none", decode="topk")
    (path,) = write_dump(topk, tmp_path / "topk.npz")
    loaded = load_dump(path)
    assert loaded.det_label is not None and loaded.n_detections == 60
    np.testing.assert_array_equal(loaded.det_label, topk.det_labels)
    # scores are the labels' sigmoid probabilities, best first within each frame
    z = loaded.det_logits[np.arange(60), -1, loaded.det_label]
    np.testing.assert_allclose(loaded.det_scores, 1 / (1 + np.exp(-z)), rtol=1e-6)
    for f in range(2):
        s = loaded.det_scores[loaded.det_frame == f]
        assert (np.diff(s) <= 1e-7).all()
    query = build_dump(model, SEEDS, max_detections=30, gt_filter="none", decode="query")
    assert query.det_label is None
    # the best detection of each frame is the same under both decodings
    for f in range(2):
        a, b = np.flatnonzero(topk.det_frame == f)[0], np.flatnonzero(query.det_frame == f)[0]
        assert topk.det_labels[a] == query.det_labels[b]
        np.testing.assert_array_equal(topk.det_boxes[a], query.det_boxes[b])
    with pytest.raises(ValueError, match="decode"):
        build_dump(model, SEEDS, decode="nms")
    # the default, "topk_nms", keeps a subset of the top-K pairs, in the same order
    nms = build_dump(model, SEEDS, max_detections=30, gt_filter="none")
    assert nms.det_label is not None and nms.n_detections <= topk.n_detections
    pairs = [(f, lab, box.tobytes()) for f, lab, box in
             zip(topk.det_frame, topk.det_labels, topk.final_boxes, strict=True)]
    kept = [(f, lab, box.tobytes()) for f, lab, box in
            zip(nms.det_frame, nms.det_labels, nms.final_boxes, strict=True)]
    positions = [pairs.index(k) for k in kept]
    assert positions == sorted(positions)
