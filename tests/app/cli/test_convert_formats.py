"""`detcal convert --from FORMAT`: a detector's own files -> dump -> fit -> calibrate."""

from __future__ import annotations

import json
import pickle

import numpy as np

from app.cli.main import main
from calibrators.io import load_dump, load_parquet


def kitti_files(root, frames=40, seed=0):
    """KITTI label folders (detections with scores, ground truth) of `frames` frames."""
    rng = np.random.default_rng(seed)
    (root / "det").mkdir()
    (root / "gt").mkdir()
    for f in range(frames):
        det, gt = [], []
        for k in range(6):
            name, (h, w, length) = [("Car", (1.5, 1.6, 3.9)), ("Pedestrian", (1.7, 0.6, 0.8)),
                                    ("Cyclist", (1.7, 0.6, 1.8))][k % 3]
            x, z, ry = rng.uniform(-15, 15), rng.uniform(5, 45), rng.uniform(-3, 3)
            gt.append(f"{name} 0 0 0 100 100 200 200 {h} {w} {length} {x:.2f} 1.65 {z:.2f} "
                      f"{ry:.2f}")
            ex, ez = rng.normal(0, 0.5, 2)
            det.append(f"{name} 0 0 0 100 100 200 200 {h} {w} {length} {x + ex:.2f} 1.65 "
                       f"{z + ez:.2f} {ry:.2f} {rng.uniform(0.3, 0.99):.3f}")
        det.append(f"Car 0 0 0 100 100 200 200 1.5 1.6 3.9 {rng.uniform(-15, 15):.2f} 1.65 "
                   f"{rng.uniform(5, 45):.2f} 0 {rng.uniform(0.01, 0.5):.3f}")
        (root / "det" / f"{f:06d}.txt").write_text("\n".join(det) + "\n")
        (root / "gt" / f"{f:06d}.txt").write_text("\n".join(gt) + "\n")


def test_kitti_to_profile_to_calibrated_results(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    kitti_files(tmp_path)
    assert main(["convert", "det", "val.npz", "--from", "kitti", "--gt", "gt"]) == 0
    dump = load_dump("val.npz")
    assert dump.n_frames == 40 and dump.n_detections == 280 and len(dump.gt_labels) == 240
    assert main(["fit", "val.npz", "--out", "profile.json", "--quiet"]) == 0
    assert main(["calibrate", "val.npz", "--profile", "profile.json", "--levels", "0.5", "0.9",
                 "--out", "results.json"]) == 0
    results = json.loads((tmp_path / "results.json").read_text())["results"]
    assert sum(len(v) for v in results.values()) == 280
    assert main(["convert", "det", "ds", "--from", "kitti", "--gt", "gt"]) == 0
    assert load_parquet(tmp_path / "ds").n_detections == 280


def test_kitti_score_and_difficulty_options(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "trk").mkdir()
    (tmp_path / "trk" / "0001.txt").write_text(
        "0,2,100.0,150.0,200.0,250.0,8.29,1.50,1.60,3.90,1.00,1.65,10.00,0.00,-1.57\n"
        "0,2,100.0,150.0,200.0,160.0,-0.5,1.50,1.60,3.90,6.00,1.65,20.00,0.00,-1.57\n")
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "0001.txt").write_text(
        "0 1 Car 0 0 0 100.0 150.0 200.0 250.0 1.50 1.60 3.90 1.00 1.65 10.00 0.00\n")
    assert main(["convert", "trk", "a.npz", "--from", "kitti"]) == 2
    assert "pass score='logit'" in capsys.readouterr().err
    assert main(["convert", "trk", "a.npz", "--from", "kitti", "--score", "logit"]) == 0
    assert load_dump("a.npz").det_logits[0, 0, 0] == 8.29
    assert main(["convert", "trk", "b.npz", "--from", "kitti", "--score", "logit", "--gt", "gt",
                 "--difficulty", "moderate"]) == 0
    assert load_dump("b.npz").n_detections == 1  # the 10 px high detection is dropped


def test_openpcdet_needs_its_class_list(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    result = [{"name": np.array(["Car"]), "score": np.array([0.7]),
               "boxes_lidar": np.array([[10.0, 1.0, -0.9, 3.9, 1.6, 1.5, 0.0]]),
               "frame_id": "000000"}]
    (tmp_path / "result.pkl").write_bytes(pickle.dumps(result))
    assert main(["convert", "result.pkl", "out.npz", "--from", "openpcdet"]) == 2
    assert "--from openpcdet" in capsys.readouterr().err
    assert main(["convert", "result.pkl", "out.npz", "--from", "openpcdet",
                 "--classes", "Car,Pedestrian,Cyclist"]) == 0
    assert load_dump("out.npz").classes == ("Car", "Pedestrian", "Cyclist")


def test_a_malformed_file_is_an_error_naming_file_and_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "det").mkdir()
    (tmp_path / "det" / "000000.txt").write_text("Car 0 0 0 1 2 3 4 1.5 1.6 3.9 1 1.65\n")
    assert main(["convert", "det", "out.npz", "--from", "kitti"]) == 2
    err = capsys.readouterr().err
    assert "det/000000.txt line 1: 13 fields" in err and "Traceback" not in err
    assert main(["convert", "det", "out.npz", "--from", "yolo"]) == 2
    assert "format must be one of" in capsys.readouterr().err


def per_box(path):
    """Calibrated score of every box of a results JSON, keyed by frame, centre and class."""
    results = json.loads(path.read_text())["results"]
    return {(token, tuple(np.round(box["translation"], 6)), box["detection_name"]):
            box["detection_score"] for token, boxes in results.items() for box in boxes}


def test_per_class_files_calibrate_every_box_as_one_folder(tmp_path, monkeypatch):
    """Files per class interleave the frames of the dump; each box still gets its own
    calibrated score."""
    monkeypatch.chdir(tmp_path)
    kitti_files(tmp_path, frames=30, seed=4)
    for name in ("Car", "Pedestrian", "Cyclist"):
        (tmp_path / "per_class" / name).mkdir(parents=True)
        for path in sorted((tmp_path / "det").glob("*.txt")):
            lines = [line for line in path.read_text().splitlines() if line.startswith(name)]
            (tmp_path / "per_class" / name / path.name).write_text(
                "".join(line + "\n" for line in lines))
    assert main(["convert", "det", "a.npz", "--from", "kitti", "--gt", "gt"]) == 0
    assert main(["convert", "per_class", "b.npz", "--from", "kitti", "--gt", "gt"]) == 0
    assert not np.all(np.diff(load_dump("b.npz").det_frame) >= 0)  # frames interleaved
    assert main(["fit", "a.npz", "--out", "profile.json", "--quiet"]) == 0
    for name in ("a", "b"):
        assert main(["calibrate", f"{name}.npz", "--profile", "profile.json",
                     "--out", f"{name}.json"]) == 0
    a, b = per_box(tmp_path / "a.json"), per_box(tmp_path / "b.json")
    assert len(a) == 210 and a == b
