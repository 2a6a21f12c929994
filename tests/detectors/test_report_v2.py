"""`detcal report-v2` (issue 13 item 4): the page's tables equal the library's outputs.

Real runs on 2 test + 2 val scenes: the baseline is the v1 lidar model (`lidar_de0.pt`, the
report's base since v2 shipped as `lidar.pt`); the "group"
model is the v1 trunk and class heads with freshly initialised, perturbed group box heads
(seed 0): true positives and a hypotheses spread to fit section 5 on, no trained v2 file.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from calibrators import evaluate, load_dump, match_dump, metrics, tp_residuals
from calibrators.covariance import hypotheses_covariance
from detectors.model import Detector
from detectors.registry import load_weights, save_weights
from detectors.report.attention import AttentionStats, Binned, binned
from detectors.report.covariance_sources import SourceRows, SourceSkip, source_rows, source_table
from detectors.report.groups import (
    LayerTrend,
    class_switches,
    collect_outputs,
    inter_group_std,
    per_layer,
    trend_interval,
)
from detectors.report.iou_bins import error_bins_table, error_rho_table, error_rhos, why_sentence
from detectors.report.sensor import report_base
from detectors.report.tables import number
from detectors.report.unified_vs_group import V2Options, V2Runs, measure_v2, v2_page
from detectors.report.unified_vs_group_tables import _interval, kept_queries, trend_verdict
from detectors.sim import SPLITS

N_TEST, N_VAL = 2, 2


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[V2Runs, V2Options, str]:
    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("report_v2")
    v1, _ = load_weights(report_base("lidar"))
    torch.manual_seed(0)
    group = Detector(replace(v1.config, head="group"))
    shapes = group.state_dict()
    group.load_state_dict({k: v for k, v in v1.state_dict().items()
                           if k in shapes and shapes[k].shape == v.shape}, strict=False)
    with torch.no_grad():   # the heads start equal (zero last layer): give them a spread
        for name, p in group.named_parameters():
            if ".boxes." in name:
                p.add_(0.05 * torch.randn_like(p))
    group_path = save_weights(group.eval(), tmp / "group.pt", {"steps": 7})
    options = V2Options(weights=group_path, baseline=report_base("lidar"),
                        test_frames=N_TEST, val_frames=N_VAL, cache=tmp / "cache")
    runs = measure_v2(options)
    return runs, options, v2_page(runs, options, "detcal report-v2 (test)", 1.0)


def test_header_names_weights_scenes_and_command(report: tuple) -> None:
    runs, _, page = report
    assert "`detcal report-v2 (test)`" in page
    for run in (runs.group, runs.baseline):
        assert f"sha256 `{run.sha256[:12]}`" in page and str(run.path) in page
    assert f"the first {N_TEST} test scenes" in page
    assert f"the first {N_VAL} val scenes" in page
    assert "7 training steps" in page


def test_ap_table_is_detcal_dump_plus_evaluate(report: tuple, tmp_path: Path) -> None:
    from app.cli.main import main

    runs, _, page = report
    out = tmp_path / "test.npz"
    assert main(["dump", "--sensor", "lidar", "--weights", str(runs.group.path), "--split",
                 "test", "--frames", str(N_TEST), "--out", str(out), "--quiet"]) == 0
    cli = evaluate(load_dump(out))
    assert cli.mean_ap == pytest.approx(runs.group.evaluation.mean_ap, abs=1e-12)
    assert cli.class_ap == pytest.approx(runs.group.evaluation.class_ap, abs=1e-12)
    g, b = runs.group.evaluation, runs.baseline.evaluation
    assert f"| **mAP** | **{g.mean_ap:.3f}** | **{b.mean_ap:.3f}** |" in page
    for c in g.class_ap:
        assert f"| {c} | {g.class_ap[c]:.3f} | {b.class_ap[c]:.3f} |" in page


def test_switch_table_equals_class_switches(report: tuple) -> None:
    runs, options, page = report
    model, _ = load_weights(runs.baseline.path)
    seeds = list(SPLITS["test"])[:N_TEST]
    out = collect_outputs(model, seeds, max_detections=options.max_detections)
    per_frame = class_switches(out.layer_logits, out.det_frame, N_TEST, options.min_score)
    assert per_frame.shape == (N_TEST, model.config.n_layers - 1)
    g = class_switches(runs.group.outputs.layer_logits, runs.group.outputs.det_frame, N_TEST,
                       options.min_score)
    for t in range(per_frame.shape[1]):
        cells = [f"{s[:, t].mean():.2f} | {np.median(s[:, t]):g} "
                 f"[{np.percentile(s[:, t], 25):g}, {np.percentile(s[:, t], 75):g}]"
                 for s in (g, per_frame)]
        assert f"| layer {t + 1} → {t + 2} | {cells[0]} | {cells[1]} |" in page


def test_group_std_table_equals_per_layer(report: tuple) -> None:
    runs, options, page = report
    out = runs.group.outputs
    assert out.group_boxes is not None and runs.baseline.outputs.group_boxes is None
    std = inter_group_std(out.group_boxes[kept_queries(out, options.min_score)])
    stats = [per_layer(std[:, :, a]) for a in range(3)]
    for i in range(out.layer_logits.shape[1]):
        cells = " | ".join(f"{number(b.median[i], 3)} [{number(b.p25[i], 3)}, "
                           f"{number(b.p75[i], 3)}]" for b in stats)
        assert f"| layer {i + 1} | {stats[0].n[i]} | {cells} |" in page


def test_attention_tables_show_the_trends(report: tuple) -> None:
    runs, _, page = report
    for run in (runs.group, runs.baseline):
        assert len(run.trends) == run.outputs.layer_logits.shape[1]
        for t in run.trends:
            assert (f"| {t.layer} | {t.stats.n_detections} | {number(t.rho_iou, 3)} | "
                    f"{_interval(t.rho_iou_interval)} | {number(t.rho_distance, 3)} | "
                    f"{_interval(t.rho_distance_interval)} | "
                    f"{100 * t.rank_deficient:.1f} % | {number(t.sample_rho_iou, 3)} | "
                    f"{number(t.sample_rho_distance, 3)} |") in page
            assert trend_verdict(t)[1] in page
        final = run.trends[-1].stats      # what separates the IoU bins, from the numbers
        assert error_bins_table(final, run.token_cell) in page
        assert error_rho_table(error_rhos(final)) in page
        assert why_sentence(final, run.token_cell) in page


def test_a_trend_one_small_bin_decides_has_a_wide_bootstrap_interval() -> None:
    rng = np.random.default_rng(0)
    # four bins of 200 detections whose medians fall clearly: a tight interval at -1
    values = np.concatenate([rng.normal(m, 0.05, 200) for m in (1.0, 0.8, 0.6, 0.4)])
    bins = np.repeat(np.arange(4), 200)
    lo, hi = trend_interval(values, bins, 4, n_boot=200)
    assert lo == hi == -1.0
    # bins 1-3 fall clearly, bin 0 holds 8 detections spread widely: its median decides rho
    # (-1 above 0.8, -0.4 between 0.6 and 0.7, 0.2 below 0.6), so the interval is wide
    few = np.concatenate([rng.normal(0.7, 0.4, 8)]
                         + [rng.normal(m, 0.02, 200) for m in (0.8, 0.7, 0.6)])
    few_bins = np.concatenate([np.zeros(8, int), np.repeat(np.arange(1, 4), 200)])
    lo, hi = trend_interval(few, few_bins, 4, n_boot=200)
    assert lo == -1.0 and hi > 0.1
    assert np.isnan(trend_interval(np.zeros(0), np.zeros(0, int), 4)[0])


def _binned(medians: list[float]) -> Binned:
    n = len(medians)
    values = np.repeat(np.asarray(medians), 5)
    return binned(values, np.repeat(np.arange(n), 5), n, tuple(f"b{i}" for i in range(n)),
                  np.zeros(5 * n, dtype=bool))


def test_trend_verdict_checks_the_three_criteria() -> None:
    stats = AttentionStats(vs_iou=_binned([9.0, 5.0, 2.0]),
                           vs_distance=_binned([1.0, 3.0, 8.0]),
                           per_layer=_binned([1.0, 1.0, 1.0]), n_detections=15, min_score=0.8)
    good = LayerTrend(3, stats, rho_iou=-1.0, rho_distance=1.0, rank_deficient=0.1)
    ok, text = trend_verdict(good)
    assert ok and "falls with IoU from 9 (b0) to 2 m⁴ (b2)" in text and "All three" in text
    assert not trend_verdict(replace(good, rank_deficient=0.25))[0]
    assert not trend_verdict(replace(good, rho_distance=float("nan")))[0]


def test_source_rows_match_the_metrics(report: tuple) -> None:
    runs, _, page = report
    assert runs.sources is not None
    by_source = {r.source: r for r in runs.sources}
    hyp = by_source["hypotheses"]
    assert isinstance(hyp, SourceRows), getattr(hyp, "reason", "")
    test = runs.group.test
    m = match_dump(test)
    res = tp_residuals(test, m, ("x", "y"))
    cov = hypotheses_covariance(test.det_hyp_boxes, test.det_hyp_scores, ("x", "y"))[m.tp]
    assert hyp.raw.n_tp == hyp.raw.n_used == len(res) > 0
    assert hyp.raw.reg_nll == pytest.approx(metrics.regression_nll(res, cov))
    assert hyp.raw.mean_md == pytest.approx(np.mean(metrics.mahalanobis(res, cov)))
    assert hyp.scaled.n_tp == len(res)
    for r in runs.sources:
        for row in (r.raw, r.scaled):
            assert (f"| {row.name} | {number(row.reg_nll)} | {number(row.mean_md)} | "
                    f"{number(row.coverage[1], 3)} | {row.n_used} / {row.n_tp} |") in page


def test_a_dump_without_hypotheses_skips_that_source(report: tuple) -> None:
    runs, _, _ = report
    base = runs.baseline.test
    out = source_rows(base, base, ("hypotheses",))
    assert isinstance(out[0], SourceSkip)
    assert "| hypotheses | skipped: " in source_table(out)


def test_cli_registers_report_v2() -> None:
    from app.cli.main import build_parser

    args = build_parser().parse_args(["report-v2", "--weights", "g.pt", "--baseline", "b.pt",
                                      "--test-frames", "3", "--threads", "1"])
    assert args.func.__name__ == "run_report_v2"
    assert (args.test_frames, args.val_frames, args.out) == (
        3, 200, Path("docs/report/detectors_v2.md"))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["report-v2", "--weights", "g.pt", "--baseline", "b.pt",
                                   "--test-frames", "0"])
