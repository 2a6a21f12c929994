"""calibrators.evaluate: nuScenes mAP / TP errors / NDS on hand-built and random dumps."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.special import logit

from calibrators.data import Dump
from calibrators.evaluation import EvaluationReport, evaluate

CLASSES = ("car", "pedestrian", "traffic_cone", "barrier")


def box(x, y, size=(1.0, 1.0, 1.0), yaw=0.0, vel=(0.0, 0.0)):
    return [x, y, 0.5, *size, yaw, *vel]


def make_dump(dets, gts, n_frames=1, classes=CLASSES, ego=None):
    """dets: (frame, class name, score, box); gts: (frame, class name, box)."""
    c = len(classes)
    labels = np.array([classes.index(d[1]) for d in dets], dtype=int)
    scores = np.array([d[2] for d in dets], dtype=float)
    logits = np.full((len(dets), c), -20.0)
    logits[np.arange(len(dets)), labels] = logit(scores)
    return Dump(classes=classes, score_mode="sigmoid",
                frame_ids=np.array([f"f{i}" for i in range(n_frames)]),
                det_frame=np.array([d[0] for d in dets], dtype=int),
                det_logits=logits.reshape(len(dets), 1, c),
                det_boxes=np.array([d[3] for d in dets], dtype=float).reshape(len(dets), 1, 9),
                gt_frame=np.array([g[0] for g in gts], dtype=int),
                gt_labels=np.array([classes.index(g[1]) for g in gts], dtype=int),
                gt_boxes=np.array([g[2] for g in gts], dtype=float).reshape(len(gts), 9),
                ego_translation=ego)


def test_perfect_detector_has_ap_one_and_zero_errors():
    dump = make_dump([(0, "car", 0.9, box(1, 1))], [(0, "car", box(1, 1))], classes=("car",))
    r = evaluate(dump)
    # (1 - 0.1) / (1 - 0.1) is 1 + 4e-16 in the devkit's arithmetic, and so here.
    assert r.ap == {"car": {t: pytest.approx(1.0) for t in ("0.5", "1.0", "2.0", "4.0")}}
    assert r.mean_ap == pytest.approx(1.0)
    assert r.tp_errors["car"] == {"trans_err": 0.0, "scale_err": 0.0, "orient_err": 0.0,
                                  "vel_err": 0.0}
    assert r.nd_score == pytest.approx((5 + 4) / 10)  # attr_err scores 0, as in the devkit


def test_false_positive_first_gives_ap_0_2_by_hand():
    # prec = [0, 1/2], rec = [0, 1]: interpolated precision r/2; AP = mean over r = 0.11..1 of
    # max(r/2 - 0.1, 0) / 0.9 = (sum_{k=21}^{100} (k/200 - 0.1)) / 90 / 0.9 = 16.2 / 81.
    dump = make_dump([(0, "car", 0.9, box(10, 0)), (0, "car", 0.8, box(0, 0))],
                     [(0, "car", box(0, 0))], classes=("car",))
    assert evaluate(dump).ap["car"]["2.0"] == pytest.approx(16.2 / 81, abs=1e-12)


def test_three_ground_truth_curve_by_hand():
    # TP, FP, TP, TP over 3 GT: rec = [1/3, 1/3, 2/3, 1], prec = [1, 1/2, 2/3, 3/4].
    gts = [(0, "car", box(0, 0)), (0, "car", box(20, 0)), (0, "car", box(40, 0))]
    dets = [(0, "car", 0.9, box(0, 0)), (0, "car", 0.8, box(-30, 0)),
            (0, "car", 0.7, box(20, 0)), (0, "car", 0.6, box(40, 0))]

    def precision(r):  # np.interp semantics: left of first point -> first value
        if r < 1 / 3:
            return 1.0
        if r < 2 / 3:
            return 0.5 + (r - 1 / 3) / (1 / 3) * (2 / 3 - 0.5)
        return 2 / 3 + (r - 2 / 3) / (1 / 3) * (0.75 - 2 / 3)

    want = sum(max(precision(k / 100) - 0.1, 0.0) for k in range(11, 101)) / 90 / 0.9
    got = evaluate(make_dump(dets, gts, classes=("car",))).ap["car"]["1.0"]
    assert got == pytest.approx(want, abs=1e-12)


def test_score_ties_follow_the_devkit_order():
    # Equal scores: the later box is visited first and takes the GT at 1.5 m, so the
    # translation error is 1.5 (a stable argsort would give 1.0).
    dump = make_dump([(0, "car", 0.5, box(1.0, 0)), (0, "car", 0.5, box(1.5, 0))],
                     [(0, "car", box(0, 0))], classes=("car",))
    r = evaluate(dump)
    assert r.tp_errors["car"]["trans_err"] == pytest.approx(1.5)
    assert r.ap["car"]["2.0"] == pytest.approx((89 * 0.9 + 0.4) / 81)


def test_equidistant_detection_takes_the_first_ground_truth():
    gts = [(0, "car", box(-1, 0, size=(1, 1, 1))), (0, "car", box(1, 0, size=(2, 2, 2)))]
    dump = make_dump([(0, "car", 0.9, box(0, 0, size=(1, 1, 1)))], gts, classes=("car",))
    assert evaluate(dump).tp_errors["car"]["scale_err"] == 0.0  # matched the 1 m cube


def test_distance_equal_to_threshold_is_a_false_positive():
    dump = make_dump([(0, "car", 0.9, box(2, 0))], [(0, "car", box(0, 0))], classes=("car",))
    ap = evaluate(dump).ap["car"]
    assert ap["2.0"] == 0.0 and ap["4.0"] == pytest.approx(1.0)


def test_classes_without_ground_truth_or_predictions_score_zero():
    dets = [(0, "car", 0.9, box(0, 0)), (0, "pedestrian", 0.9, box(5, 5))]  # no pedestrian GT
    gts = [(0, "car", box(0, 0)), (0, "traffic_cone", box(9, 9))]  # no cone prediction
    r = evaluate(make_dump(dets, gts))
    assert r.ap["pedestrian"] == r.ap["traffic_cone"] == r.ap["barrier"] == {
        "0.5": 0.0, "1.0": 0.0, "2.0": 0.0, "4.0": 0.0}
    assert r.mean_ap == pytest.approx(0.25)
    assert r.tp_errors["pedestrian"] == {m: 1.0 for m in r.tp_errors["pedestrian"]}
    cone, barrier = r.tp_errors["traffic_cone"], r.tp_errors["barrier"]
    assert math.isnan(cone["orient_err"]) and math.isnan(cone["vel_err"])
    assert cone["trans_err"] == 1.0 and barrier["orient_err"] == 1.0
    assert math.isnan(barrier["vel_err"])
    # mean errors: nan-mean over classes; NDS = (5 mAP + sum(1 - min(1, err))) / 10
    assert r.mean_tp_errors["trans_err"] == pytest.approx(3 / 4)
    assert r.mean_tp_errors["vel_err"] == pytest.approx(1 / 2)
    assert r.nd_score == pytest.approx((5 * 0.25 + 0.25 + 0.25 + 1 / 3 + 0.5) / 10)


def test_empty_frames_change_nothing():
    dets = [(0, "car", 0.9, box(0, 0)), (0, "car", 0.4, box(3, 0))]
    gts = [(0, "car", box(0.3, 0)), (0, "car", box(9, 0))]
    base = evaluate(make_dump(dets, gts, classes=("car",)))
    shifted = [(d[0] + 1,) + d[1:] for d in dets]
    more = evaluate(make_dump(shifted + [(3, "car", 0.1, box(50, 50))],
                              [(g[0] + 1,) + g[1:] for g in gts] + [(2, "car", box(1, 1))],
                              n_frames=5, classes=("car",)))
    assert base.n_frames == 1 and more.n_frames == 5
    nothing = evaluate(make_dump(shifted, [(g[0] + 1,) + g[1:] for g in gts], n_frames=4,
                                 classes=("car",)))
    assert nothing.ap == base.ap and nothing.tp_errors == base.tp_errors
    assert more.ap != base.ap  # the extra GT and FP do count


def test_range_filter_measured_from_the_ego():
    ego = np.array([[100.0, -50.0, 0.0]])
    dets = [(0, "car", 0.9, box(149, -50)), (0, "car", 0.8, box(151, -50)),
            (0, "pedestrian", 0.9, box(100, -11))]
    gts = [(0, "car", box(149, -50)), (0, "car", box(151, -50)),
           (0, "pedestrian", box(100, -9.5))]
    r = evaluate(make_dump(dets, gts, ego=ego))
    assert r.n_detections_evaluated == 2 and r.n_gt_evaluated == 1
    assert r.ap["car"]["0.5"] == pytest.approx(1.0)  # the car at 51 m and its GT are both gone
    assert r.ap["pedestrian"]["4.0"] == 0.0  # detection at 39 m, its GT at 40.5 m removed
    unfiltered = evaluate(make_dump(dets, gts, ego=ego), class_range=None)
    assert unfiltered.n_gt_evaluated == 3
    assert unfiltered.ap["pedestrian"]["4.0"] == pytest.approx(1.0)
    assert unfiltered.class_range["car"] is None and r.class_range["car"] == 50.0


def test_orientation_period_and_velocity():
    dets = [(0, "car", 0.9, box(0, 0, yaw=np.pi, vel=(3, 4))),
            (0, "barrier", 0.9, box(5, 5, yaw=np.pi))]
    gts = [(0, "car", box(0, 0)), (0, "barrier", box(5, 5))]
    r = evaluate(make_dump(dets, gts))
    assert r.tp_errors["car"]["orient_err"] == pytest.approx(np.pi)
    assert r.tp_errors["car"]["vel_err"] == pytest.approx(5.0)
    assert r.tp_errors["barrier"]["orient_err"] == pytest.approx(0.0, abs=1e-12)


def test_score_override_and_box_limit():
    dets = [(0, "car", 0.9, box(10, 0)), (0, "car", 0.8, box(0, 0))]
    dump = make_dump(dets, [(0, "car", box(0, 0))], classes=("car",))
    # TP then FP: precision 1 below recall 1 and 1/2 at recall 1 (np.interp at the last point)
    assert evaluate(dump, scores=[0.1, 0.8]).ap["car"]["2.0"] == pytest.approx(80.5 / 81)
    with pytest.raises(ValueError, match="max_boxes_per_frame=1"):
        evaluate(dump, max_boxes_per_frame=1)
    assert evaluate(dump, max_boxes_per_frame=None).n_detections == 2
    with pytest.raises(ValueError, match="scores has NaN"):
        evaluate(dump, scores=[np.nan, 0.5])
    with pytest.raises(ValueError, match="thresholds"):
        evaluate(dump, thresholds=(1.0, -1.0))


def test_report_is_strict_json():
    r = evaluate(make_dump([(0, "car", 0.9, box(0, 0))], [(0, "car", box(0, 0))]))
    assert isinstance(r, EvaluationReport)
    data = json.loads(r.to_json())
    assert data["tp_errors"]["traffic_cone"]["orient_err"] is None
    assert data["ap"]["car"]["2.0"] == pytest.approx(1.0)
    assert data["thresholds"] == [0.5, 1.0, 2.0, 4.0]
    assert set(data) >= {"mean_ap", "ap", "tp_errors", "mean_tp_errors", "nd_score",
                         "n_frames", "n_detections", "thresholds"}


# -- an independent, straightforward re-implementation of the devkit loop ----------------------
def reference_evaluate(dump, scores, class_range, ths=(0.5, 1.0, 2.0, 4.0)):
    ego = np.zeros((dump.n_frames, 3)) if dump.ego_translation is None else dump.ego_translation
    preds = _in_range(dump, ego, class_range, dump.final_boxes, dump.det_frame, dump.det_labels,
                      scores)
    gts = _in_range(dump, ego, class_range, dump.gt_boxes, dump.gt_frame, dump.gt_labels,
                    [-1.0] * len(dump.gt_boxes))
    ap, tpe = {}, {}
    for name in dump.classes:
        ap[name] = {}
        for th in ths:
            md = _accumulate(preds, gts, name, th)
            p = np.zeros(101) if md is None else md[0].copy()
            ap[name][str(th)] = float(np.mean(np.clip(p[11:] - 0.1, 0, None))) / 0.9
        tpe[name] = _tp_errors(name, _accumulate(preds, gts, name, 2.0))
    return ap, tpe


def _in_range(dump, ego, class_range, rows, frames, labels, confs):
    """The devkit's boxes per frame, within their class's range of the ego."""
    out = {f: [] for f in range(dump.n_frames)}
    for k in range(len(rows)):
        f, name = int(frames[k]), dump.classes[labels[k]]
        rel = rows[k][:2] - ego[f][:2]
        if math.sqrt(rel[0] ** 2 + rel[1] ** 2) < class_range[name]:
            out[f].append(dict(row=rows[k], name=name, conf=confs[k]))
    return out


def _accumulate(preds, gts, name, th):
    """The devkit's `accumulate` for one class and threshold: precision and confidence on the
    101-point recall grid, and the TP errors' cumulative means; None without a match."""
    npos = sum(1 for f in gts for b in gts[f] if b["name"] == name)
    if npos == 0:
        return None
    plist = [(f, b) for f in preds for b in preds[f] if b["name"] == name]
    confs = [b["conf"] for _, b in plist]
    order = [i for (v, i) in sorted((v, i) for (i, v) in enumerate(confs))][::-1]
    taken, tp, fp, conf, err = set(), [], [], [], {m: [] for m in ERRS}
    for i in order:
        f, p = plist[i]
        best, min_dist = _closest(gts[f], taken, f, name, p)
        conf.append(p["conf"])
        if min_dist < th:
            taken.add((f, best))
            tp.append(1)
            fp.append(0)
            _match_errors(err, gts[f][best]["row"], p, name, min_dist)
        else:
            tp.append(0)
            fp.append(1)
    if not err["trans_err"]:
        return None
    tps, fps = np.cumsum(tp).astype(float), np.cumsum(fp).astype(float)
    rec_grid = np.linspace(0, 1, 101)
    prec = np.interp(rec_grid, tps / npos, tps / (tps + fps), right=0)
    conf_i = np.interp(rec_grid, tps / npos, np.array(conf), right=0)
    res = {}
    for m in ERRS[:-1]:
        x = np.array(err[m])
        cm = np.cumsum(x) / np.arange(1, len(x) + 1)
        res[m] = np.interp(conf_i[::-1], err["conf"][::-1], cm[::-1])[::-1]
    return prec, conf_i, res


def _closest(frame_gts, taken, f, name, p):
    """(index, distance) of the closest untaken ground truth of `name` in the frame."""
    best, min_dist = None, math.inf
    for j, g in enumerate(frame_gts):
        if g["name"] == name and (f, j) not in taken:
            d = math.hypot(*(p["row"][:2] - g["row"][:2]))
            if d < min_dist:
                best, min_dist = j, d
    return best, min_dist


def _match_errors(err, g, p, name, min_dist):
    """Append one true positive's translation, scale, orientation and velocity errors."""
    q = p["row"]
    inter = np.prod(np.minimum(g[3:6], q[3:6]))
    period = math.pi if name == "barrier" else 2 * math.pi
    dyaw = (g[6] - q[6] + period / 2) % period - period / 2
    dyaw = dyaw - 2 * math.pi if dyaw > math.pi else dyaw
    err["trans_err"].append(min_dist)
    err["scale_err"].append(1 - inter / (np.prod(g[3:6]) + np.prod(q[3:6]) - inter))
    err["orient_err"].append(abs(dyaw))
    err["vel_err"].append(math.hypot(*(q[7:9] - g[7:9])))
    err["conf"].append(p["conf"])


def _tp_errors(name, md):
    """The devkit's TP errors of one class at 2 m (NaN where the class has none)."""
    out = {}
    for m in ERRS[:-1]:
        if (name == "traffic_cone" and m in ("orient_err", "vel_err")) or (
                name == "barrier" and m == "vel_err"):
            out[m] = math.nan
            continue
        last = 0 if md is None or not md[1].any() else int(np.nonzero(md[1])[0][-1])
        out[m] = 1.0 if md is None or last < 11 else float(np.mean(md[2][m][11:last + 1]))
    return out


ERRS = ("trans_err", "scale_err", "orient_err", "vel_err", "conf")


def random_dump(seed):
    rng = np.random.default_rng(seed)
    f, c = 8, len(CLASSES)
    ego = np.column_stack([rng.uniform(-100, 100, (f, 2)), np.zeros(f)])
    gt_frame = rng.integers(0, f, 60)
    gt_labels = rng.integers(0, c, 60)
    gt = np.column_stack([ego[gt_frame, :2] + rng.uniform(-45, 45, (60, 2)), np.zeros(60),
                          rng.uniform(0.5, 3, (60, 3)), rng.uniform(-3, 3, 60),
                          rng.normal(0, 2, (60, 2))])
    pick = rng.integers(0, 60, 150)
    det = gt[pick] + np.column_stack([rng.normal(0, 1.2, (150, 2)), np.zeros(150),
                                      rng.normal(0, 0.2, (150, 3)).clip(-0.4, 0.4),
                                      rng.normal(0, 0.5, 150), rng.normal(0, 1, (150, 2))])
    det_labels = np.where(rng.random(150) < 0.8, gt_labels[pick], rng.integers(0, c, 150))
    fp = rng.random(150) < 0.3
    det[fp, :2] = ego[gt_frame[pick[fp]], :2] + rng.uniform(-45, 45, (fp.sum(), 2))
    scores = np.round(rng.uniform(0.05, 0.95, 150), 1)  # ties
    logits = np.full((150, c), -20.0)
    logits[np.arange(150), det_labels] = logit(scores)
    dump = Dump(classes=CLASSES, score_mode="sigmoid", frame_ids=[f"s{i}" for i in range(f)],
                det_frame=gt_frame[pick], det_logits=logits[:, None], det_boxes=det[:, None],
                gt_frame=gt_frame, gt_labels=gt_labels, gt_boxes=gt, ego_translation=ego)
    return dump, scores


@pytest.mark.parametrize("seed", range(5))
def test_random_dumps_match_the_reference_loop(seed):
    dump, scores = random_dump(seed)
    ranges = {"car": 40.0, "pedestrian": 30.0, "traffic_cone": 25.0, "barrier": 35.0}
    r = evaluate(dump, scores=scores, class_range=ranges)
    ap, tpe = reference_evaluate(dump, scores, ranges)
    assert r.ap == ap  # bit for bit
    for name in CLASSES:
        for m, v in tpe[name].items():
            got = r.tp_errors[name][m]
            assert (math.isnan(v) and math.isnan(got)) or got == pytest.approx(v, abs=1e-12)
    assert r.mean_ap == pytest.approx(np.mean([np.mean(list(a.values())) for a in ap.values()]))
    assert 0 < r.mean_ap < 1
