"""calibrators.io.kitti: KITTI object / tracking label text with scores, KITTI ground truth.

Fixtures are label lines written by hand from the devkit readme (type truncated occluded
alpha bbox[4] h w l x y z rotation_y [score]; tracking: frame track_id first), expected boxes
worked out by hand from its conventions (location = bottom centre, rectified camera 0).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibrators.core.errors import FieldError
from calibrators.io import load_dump
from calibrators.io.kitti import load_kitti
from tests.calibrators.io.reader_checks import (
    assert_reads_or_refuses,
    assert_same_content,
    npz_round_trip,
)

# Car: bbox 100..200 x 150..250, h 1.5 w 1.6 l 3.9 at (1, 1.65, 10), ry 0, score 0.93.
CAR = "Car 0.00 0 -1.57 100.0 150.0 200.0 250.0 1.50 1.60 3.90 1.00 1.65 10.00 0.00"
PED = "Pedestrian 0.00 0 0.20 300.0 150.0 320.0 250.0 1.80 0.60 0.80 -3.00 1.70 20.00 1.00"
DONTCARE = "DontCare -1 -1 -10 500.0 150.0 600.0 250.0 -1 -1 -1 -1000 -1000 -1000 -10"
CALIB = """P0: 7.0e+02 0 6.0e+02 0 0 7.0e+02 1.8e+02 0 0 0 1 0
P1: 7.0e+02 0 6.0e+02 -3.8e+02 0 7.0e+02 1.8e+02 0 0 0 1 0
P2: 7.0e+02 0 6.0e+02 4.5e+01 0 7.0e+02 1.8e+02 2.1e-01 0 0 1 2.7e-03
P3: 7.0e+02 0 6.0e+02 -3.3e+02 0 7.0e+02 1.8e+02 2.3e+00 0 0 1 3.6e-03
R0_rect: 1 0 0 0 1 0 0 0 1
Tr_velo_to_cam: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27
Tr_imu_to_velo: 1 0 0 -0.81 0 1 0 0.32 0 0 1 -0.80
"""


def write(folder, files):
    folder.mkdir(parents=True, exist_ok=True)
    for name, lines in files.items():
        (folder / name).write_text("".join(line + "\n" for line in lines))
    return folder


def test_object_fields_in_camera_axes(tmp_path):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.93", PED + " 0.40"],
                                   "000001.txt": []})
    dump = load_kitti(det)
    assert dump.classes == ("Car", "Pedestrian", "Cyclist") and dump.score_mode == "sigmoid"
    assert dump.frame_ids.tolist() == ["000000", "000001"] and len(dump.gt_labels) == 0
    # No calib: x = z_cam, y = -x_cam, z = -(y_cam - h/2); yaw = -ry - pi/2.
    np.testing.assert_allclose(dump.final_boxes[0],
                               [10.0, -1.0, -0.9, 1.6, 3.9, 1.5, -math.pi / 2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(dump.final_boxes[1, :3], [20.0, 3.0, -0.8], atol=1e-12)
    assert dump.final_boxes[1, 6] == pytest.approx(-1.0 - math.pi / 2)
    np.testing.assert_allclose(dump.det_scores, [0.93, 0.40], atol=1e-12)
    assert dump.det_labels.tolist() == [0, 1]


@pytest.mark.parametrize("ry, yaw", [(math.pi / 2, math.pi), (-math.pi / 2, 0.0),
                                     (math.pi, math.pi / 2)])
def test_rotation_y_to_yaw(tmp_path, ry, yaw):
    line = CAR.rsplit(" ", 1)[0] + f" {ry!r} 0.5"
    dump = load_kitti(write(tmp_path / "d", {"000007.txt": [line]}))
    assert math.cos(dump.final_boxes[0, 6] - yaw) == pytest.approx(1.0)


def test_calib_maps_to_lidar(tmp_path):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.93"]})
    calib = write(tmp_path / "calib", {"000000.txt": CALIB.splitlines()})
    dump = load_kitti(det, calib=calib)
    # velo = inv(Tr_velo_to_cam) (centre (1, 0.9, 10)): x = 10 + 0.27, y = -1, z = -(0.9 + 0.08)
    np.testing.assert_allclose(dump.final_boxes[0],
                               [10.27, -1.0, -0.98, 1.6, 3.9, 1.5, -math.pi / 2, 0, 0],
                               atol=1e-9)
    one = load_kitti(det, calib=calib / "000000.txt")  # one file for every frame
    np.testing.assert_allclose(one.final_boxes, dump.final_boxes)


def test_tracking_frames_and_ground_truth(tmp_path):
    det = write(tmp_path / "det", {"0004.txt": ["3 1 " + CAR + " 0.9", "5 2 " + PED + " 0.6",
                                                "3 7 " + PED + " 0.2"]})
    gt = write(tmp_path / "gt", {"0004.txt": ["3 1 " + CAR, "4 -1 " + DONTCARE]})
    dump = load_kitti(det, gt)
    assert dump.frame_ids.tolist() == ["0004/000003", "0004/000004", "0004/000005"]
    assert dump.frame_ids[dump.det_frame].tolist() == ["0004/000003", "0004/000005",
                                                       "0004/000003"]
    assert dump.frame_ids[dump.gt_frame].tolist() == ["0004/000003"]


def test_one_folder_per_class_concatenated(tmp_path):
    write(tmp_path / "res" / "Car" / "data", {"000000.txt": [CAR + " 0.9"],
                                              "000001.txt": [CAR + " 0.8"]})
    write(tmp_path / "res" / "Pedestrian" / "data", {"000000.txt": [PED + " 0.7"]})
    dump = load_kitti(tmp_path / "res")
    assert dump.frame_ids.tolist() == ["000000", "000001"]
    assert sorted(zip(dump.det_frame.tolist(), dump.det_labels.tolist(),
                      strict=True)) == \
        [(0, 0), (0, 1), (1, 0)]
    both = load_kitti([tmp_path / "res" / "Car", tmp_path / "res" / "Pedestrian"])
    assert_same_content(both, dump)


def test_single_files_of_other_names(tmp_path):
    det = write(tmp_path / "det", {"000004.txt": [CAR + " 0.9"]})
    gt = write(tmp_path / "gt", {"labels.txt": [CAR]})
    dump = load_kitti(det / "000004.txt", gt / "labels.txt")
    assert dump.frame_ids.tolist() == ["000004", "labels"]  # a file is a frame
    calib = write(tmp_path / "calib", {"000004.txt": CALIB.splitlines()})
    with pytest.raises(FieldError, match=r"calib/labels.txt is missing"):
        load_kitti(det, gt / "labels.txt", calib=calib)


def test_ab3dmot_detection_files_per_class(tmp_path):
    # AB3DMOT README: frame, type (1 Pedestrian, 2 Car, 3 Cyclist), 2D bbox x1 y1 x2 y2, score,
    # 3D bbox h w l x y z rot_y, alpha; one comma-separated file per class and sequence.
    write(tmp_path / "dets" / "pointrcnn_Car_val", {"0001.txt": [
        "0,2,100.0,150.0,200.0,250.0,8.29,1.50,1.60,3.90,1.00,1.65,10.00,0.00,-1.57",
        "3,2,100.0,150.0,200.0,250.0,-0.71,1.50,1.60,3.90,2.00,1.65,20.00,0.50,-1.0"]})
    write(tmp_path / "dets" / "pointrcnn_Pedestrian_val", {"0001.txt": [
        "0, 1, 300.0, 150.0, 320.0, 250.0, 2.5, 1.80, 0.60, 0.80, -3.00, 1.70, 20.00, 1.0, 0.2"]})
    gt = write(tmp_path / "label_02", {"0001.txt": ["0 4 " + CAR, "0 5 " + PED]})
    dump = load_kitti(tmp_path / "dets", gt, score="logit")
    assert dump.frame_ids.tolist() == ["0001/000000", "0001/000003"]
    car = load_kitti(write(tmp_path / "obj", {"0001.txt": [CAR + " 0.9"]}))
    np.testing.assert_allclose(dump.final_boxes[0], car.final_boxes[0])
    assert dump.det_labels.tolist() == [0, 0, 1] and len(dump.gt_labels) == 2
    np.testing.assert_allclose(dump.det_logits[[0, 1, 2], 0, [0, 0, 1]], [8.29, -0.71, 2.5])
    bad = write(tmp_path / "bad", {"0001.txt": ["0,4,1,2,3,4,0.5,1,1,1,1,1,1,0,0"]})
    with pytest.raises(FieldError, match=r"bad/0001.txt line 1: type_id must be 1"):
        load_kitti(bad, score="logit")
    short = write(tmp_path / "short", {"0001.txt": ["0,2,1,2,3,4,0.5,1,1,1,1,1,1,0"]})
    with pytest.raises(FieldError, match=r"line 1: 14 comma-separated fields; AB3DMOT"):
        load_kitti(short, score="logit")


def test_ground_truth_only_for_the_detections_frames(tmp_path):
    det = write(tmp_path / "det", {"000001.txt": [CAR + " 0.9"]})
    gt = write(tmp_path / "gt", {"000000.txt": [PED], "000001.txt": [CAR, "Truck" + CAR[3:]]})
    dump = load_kitti(det, gt)
    assert dump.frame_ids.tolist() == ["000001"]
    assert dump.gt_labels.tolist() == [0]  # the Truck is no class: not ground truth


def test_dontcare_ignores_unmatched_detections_inside(tmp_path):
    inside = "Car 0 0 0 510.0 160.0 590.0 240.0 1.5 1.6 3.9 8.0 1.65 30.0 0.0 0.8"
    half = "Car 0 0 0 560.0 160.0 660.0 240.0 1.5 1.6 3.9 9.0 1.65 30.0 0.0 0.7"
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9", inside, half]})
    gt = write(tmp_path / "gt", {"000000.txt": [CAR, DONTCARE]})
    dump = load_kitti(det, gt)
    # inside: 100 % of its box in the DontCare region -> ignored; half: 40 % < 0.7 -> an FP.
    assert sorted(dump.det_scores.round(6).tolist()) == [0.7, 0.9]
    assert len(dump.gt_labels) == 1  # DontCare is no ground truth


def test_dontcare_keeps_a_matched_detection(tmp_path):
    in_region = CAR.replace("100.0 150.0 200.0 250.0", "510.0 160.0 590.0 240.0")
    det = write(tmp_path / "det", {"000000.txt": [in_region + " 0.9"]})
    gt = write(tmp_path / "gt", {"000000.txt": [in_region, DONTCARE]})
    assert load_kitti(det, gt).n_detections == 1  # a true positive stays one


def test_neighbouring_classes_are_ignored(tmp_path):
    van = "Van" + CAR[3:]
    sitting = "Person_sitting" + PED[10:]
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9", PED + " 0.8"]})
    gt = write(tmp_path / "gt", {"000000.txt": [van, sitting]})
    dump = load_kitti(det, gt)
    assert dump.n_detections == 0 and len(dump.gt_labels) == 0
    # With Van a class of its own it is ground truth, and the Car on it a false positive.
    own = load_kitti(det, gt, classes=("Car", "Van", "Pedestrian"))
    assert own.det_labels.tolist() == [0] and own.gt_labels.tolist() == [1]


def test_truck_ground_truth_is_no_ignore_region(tmp_path):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9"]})
    gt = write(tmp_path / "gt", {"000000.txt": ["Truck" + CAR[3:]]})
    dump = load_kitti(det, gt)
    assert dump.n_detections == 1 and len(dump.gt_labels) == 0  # a false positive


def test_class_map_and_explicit_classes(tmp_path):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9", "Cyclist" + PED[10:] + " 0.5",
                                                  "Van" + CAR[3:] + " 0.3"]})
    dump = load_kitti(det, classes=("car", "bicycle"),
                      class_map={"Car": "car", "Van": "car", "Cyclist": "bicycle"})
    assert dump.classes == ("car", "bicycle") and dump.det_labels.tolist() == [0, 1, 0]
    with pytest.raises(FieldError, match="maps 'Car' to 'auto'"):
        load_kitti(det, classes=("car",), class_map={"Car": "auto"})


def test_scores_as_logits(tmp_path):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 2.5", PED + " -1.0"]})
    with pytest.raises(FieldError, match=r"det/000000.txt line 1: score 2.5 is not a "
                                         r"probability .*score='logit'"):
        load_kitti(det)
    dump = load_kitti(det, score="logit")
    np.testing.assert_allclose(dump.det_logits[[0, 1], 0, [0, 1]], [2.5, -1.0])


def test_round_trip_and_dispatch(tmp_path):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9", PED + " 0.4"]})
    gt = write(tmp_path / "gt", {"000000.txt": [CAR]})
    dump = load_kitti(det, gt)
    assert_same_content(npz_round_trip(dump), dump)
    assert_same_content(load_dump(det, format="kitti", ground_truth=gt), dump)


@pytest.mark.parametrize("line, match", [
    (CAR, r"det/000000.txt line 2: 15 fields where the file's first line has 16"),
    (CAR + " 0.5 7", r"line 2: 17 fields"),
    (CAR.replace("1.60", "wide") + " 0.5", r"line 2: dimensions must be a number, got 'wide'"),
    (CAR.replace("10.00", "nan") + " 0.5", r"line 2: location is 'nan'; it must be finite"),
    (CAR.replace("1.50", "0.0") + " 0.5", r"line 2: dimensions .* must be > 0"),
    ("Bus" + CAR[3:] + " 0.5", r"line 2: type 'Bus' is neither a KITTI type"),
])
def test_malformed_lines_name_file_line_and_field(tmp_path, line, match):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9", line]})
    with pytest.raises(FieldError, match=match):
        load_kitti(det)


def test_malformed_files(tmp_path):
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9"]})
    with pytest.raises(FieldError, match="need a score column"):
        load_kitti(write(tmp_path / "noscore", {"000000.txt": [CAR]}))
    with pytest.raises(FieldError, match=r"line 1: 8 fields; KITTI labels have 15"):
        load_kitti(write(tmp_path / "short", {"000000.txt": [CAR[:40]]}))
    with pytest.raises(FieldError, match=r"gt/000000.txt is missing"):
        load_kitti(det, write(tmp_path / "gt", {"000009.txt": [CAR]}))
    with pytest.raises(FieldError, match=r"calib/000000.txt: missing Tr_velo_to_cam"):
        load_kitti(det, calib=write(tmp_path / "calib", {"000000.txt": CALIB.splitlines()[:5]}))
    bad = CALIB.replace("R0_rect: 1 0 0 0 1 0 0 0 1", "R0_rect: 1 0 0 0 1 0 0 0")
    with pytest.raises(FieldError, match=r"cal2/000000.txt line 5: R0_rect must be 9 finite"):
        load_kitti(det, calib=write(tmp_path / "cal2", {"000000.txt": bad.splitlines()}))
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "000000.txt").write_bytes(b"Car \xff\xfe")
    with pytest.raises(FieldError, match=r"bin/000000.txt: not UTF-8"):
        load_kitti(tmp_path / "bin")
    with pytest.raises(FieldError, match="limit of 50 bytes"):
        load_kitti(det, max_bytes=50)
    with pytest.raises(FieldError, match="no such file"):
        load_kitti(tmp_path / "nothing")
    track = write(tmp_path / "trk", {"0001.txt": ["0 1 " + CAR + " 0.9"]})
    with pytest.raises(FieldError, match="ground truth is object labels but the detections "
                                         "are tracking"):
        load_kitti(track, write(tmp_path / "gt2", {"0001.txt": [CAR]}))
    with pytest.raises(FieldError, match=r"line 1: frame must be a whole number"):
        load_kitti(write(tmp_path / "trk2", {"0001.txt": ["x 1 " + CAR + " 0.9"]}))
    with pytest.raises(FieldError, match=r"line 1: track_id must be a whole number >= -1"):
        load_kitti(write(tmp_path / "trk3", {"0001.txt": ["0 --1 " + CAR + " 0.9"]}))


LINES = [f"Car 0 0 0 {100 + 9 * k}.0 150.0 {160 + 9 * k}.0 250.0 1.5 1.6 3.9 "
         f"{k * 0.7 - 3:.2f} 1.65 {8 + k * 1.3:.2f} {k * 0.2:.2f} {0.05 + k * 0.04:.2f}"
         for k in range(12)]


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2), st.integers(0, 11)), min_size=1, max_size=20,
                unique_by=lambda t: t[1]), st.randoms(use_true_random=False))
def test_order_and_interleaving_do_not_change_content(tmp_path_factory, picks, rnd):
    """The same detections, written in another order and split across per-class files as a
    pipeline interleaves frames, give the same dump content per detection."""
    base = tmp_path_factory.mktemp("perm")
    frames = {f"00000{f}.txt": [LINES[k] for g, k in picks if g == f] for f in range(3)}
    region = DONTCARE.replace("500.0 150.0 600.0", "130.0 150.0 400.0")  # holds some lines
    gt = write(base / "gt", {name: [LINES[0].rsplit(" ", 1)[0], region] for name in frames})
    ref = load_kitti(write(base / "a", frames), gt)
    shuffled = {name: rnd.sample(lines, len(lines)) for name, lines in frames.items()}
    parts: dict[str, dict[str, list[str]]] = {"p0": {}, "p1": {}}
    for name, lines in shuffled.items():
        cut = rnd.randint(0, len(lines))
        parts["p0"][name], parts["p1"][name] = lines[:cut], lines[cut:]
    other = load_kitti([write(base / "b" / p, files) for p, files in rnd.sample(
        sorted(parts.items()), 2)], gt)
    assert_same_content(other, ref)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10**6), st.integers(0, 10**6))
def test_damaged_file_is_read_or_refused(tmp_path_factory, cut, flip):
    folder = tmp_path_factory.mktemp("dmg")
    data = "".join(line + "\n" for line in (CAR + " 0.9", PED + " 0.4", DONTCARE + " 0.1"))
    assert_reads_or_refuses(folder / "000000.txt", data.encode(), cut, flip, load_kitti)


def test_difficulty_levels_as_kitti(tmp_path):
    # Car ground truth 100 px high, fully visible; a second one 30 px high (moderate, not easy)
    # and a third one largely occluded (hard only).
    low = "Car 0.00 0 0 300.0 150.0 360.0 180.0 1.5 1.6 3.9 -5.00 1.65 30.00 0.00"
    hidden = "Car 0.00 2 0 400.0 150.0 480.0 250.0 1.5 1.6 3.9 6.00 1.65 25.00 0.00"
    gt = write(tmp_path / "gt", {"000000.txt": [CAR, low, hidden]})
    det = write(tmp_path / "det", {"000000.txt": [CAR + " 0.9", low + " 0.8", hidden + " 0.7"]})
    counts = {level: (load_kitti(det, gt, difficulty=level).n_detections,
                      len(load_kitti(det, gt, difficulty=level).gt_labels))
              for level in (None, "easy", "moderate", "hard")}
    # easy: the low box is too small (its detection too), the hidden one too occluded (its
    # detection on ignored ground truth): one of each stays
    assert counts == {None: (3, 3), "easy": (1, 1), "moderate": (2, 2), "hard": (3, 3)}
    with pytest.raises(FieldError, match="difficulty must be one of"):
        load_kitti(det, gt, difficulty="medium")
