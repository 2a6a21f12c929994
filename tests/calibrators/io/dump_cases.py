"""Small dumps, NPZ archives and devkit boxes that the io tests build (and the service's
upload and feedback tests reuse)."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np

from calibrators.data import Dump

CLASSES = ("car", "pedestrian", "traffic_cone")


def arrays(seed=0, n=12, g=5, f=3, layers=2, mode="sigmoid", optional=True):
    """The raw NPZ arrays of a small valid dump."""
    rng = np.random.default_rng(seed)
    width = len(CLASSES) + (mode == "softmax")
    boxes = np.column_stack([rng.uniform(-20, 20, (n * layers, 3)),
                             rng.uniform(0.5, 3, (n * layers, 3)),
                             rng.uniform(-3.1, 3.1, n * layers), rng.normal(0, 1, (n * layers, 2))])
    gt = np.column_stack([rng.uniform(-20, 20, (g, 3)), rng.uniform(0.5, 3, (g, 3)),
                          rng.uniform(-3.1, 3.1, g), rng.normal(0, 1, (g, 2))])
    out = {
        "classes": np.array(CLASSES), "score_mode": np.array(mode),
        "frame_ids": np.array([f"tok{i}" for i in range(f)]),
        "det_frame": rng.integers(0, f, n), "det_logits": rng.normal(0, 2, (n, layers, width)),
        "det_boxes": boxes.reshape(n, layers, 9),
        "gt_frame": rng.integers(0, f, g), "gt_labels": rng.integers(0, len(CLASSES), g),
        "gt_boxes": gt,
    }
    if optional:
        a = rng.normal(0, 1, (n, 2, 2))
        out["det_cov"] = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(2)
        out["cov_dims"] = np.array(["x", "y"])
        out["ego_translation"] = rng.uniform(-500, 500, (f, 3))
    return out


def write(path, content):
    np.savez(path, **content)
    return path


def assert_same(a: Dump, b: Dump):
    assert a.classes == b.classes and a.score_mode == b.score_mode and a.cov_dims == b.cov_dims
    for key in ("frame_ids", "det_frame", "det_logits", "det_boxes", "gt_frame", "gt_labels",
                "gt_boxes", "ego_translation", "det_cov"):
        x, y = getattr(a, key), getattr(b, key)
        assert (x is None) == (y is None), key
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=key)


def hostile_npz(content: dict, fake: dict | None = None) -> bytes:
    """`content` as deflated NPZ bytes; each `fake` key -> (header shape, dtype, zero bytes) is
    written with that .npy header and that many zero bytes of data, whatever the shape says
    (a few MB of zeros deflate to a few kB)."""
    fake = fake or {}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for key, arr in content.items():
            if key not in fake:
                with zf.open(f"{key}.npy", "w") as fh:
                    np.lib.format.write_array(fh, np.asarray(arr), allow_pickle=True)
        for key, (shape, dtype, zeros) in fake.items():
            with zf.open(f"{key}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array_header_1_0(fh, {
                    "descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                    "fortran_order": False, "shape": shape})
                for start in range(0, zeros, 2**20):
                    fh.write(bytes(min(2**20, zeros - start)))
    return buf.getvalue()


def nusc_dump(seed=0, ego=True, cov=True):
    content = arrays(seed=seed, n=30, g=10, f=4, layers=1, optional=True)
    if not ego:
        del content["ego_translation"]
    if not cov:
        del content["det_cov"]
    g = len(content["gt_boxes"])  # the first g detections find their ground truth
    content["det_frame"][:g] = content["gt_frame"]
    content["det_boxes"][:g, 0] = content["gt_boxes"] + 0.3
    content["det_logits"][np.arange(g), 0, content["gt_labels"]] += 10.0
    fields = {k: (str(v) if k == "score_mode" else v) for k, v in content.items()}
    return Dump(**fields)


def devkit_box(token, name, xyz, score=0.5, yaw=0.0, **extra):
    return {"sample_token": token, "translation": list(xyz), "size": [2.0, 4.0, 1.5],
            "rotation": [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))],
            "velocity": [1.0, 0.0], "detection_name": name, "detection_score": score,
            "attribute_name": "", **extra}


def write_pair(tmp_path, results, gt, meta=None):
    res, g = tmp_path / "r.json", tmp_path / "g.json"
    res.write_text(json.dumps({"meta": meta or {}, "results": results}))
    g.write_text(json.dumps({"meta": {}, "results": gt}))
    return res, g
