"""The window probe of `detcal report-v2 --probe-windows W ...` (issue 13, seed 000).

A windowed cross-attention (`DetectorConfig.attn_window`) bounds where a query can look. To
see whether the window, and not the data, decides seed 000's trends, the group model's own
weights run again with each wider window W at inference (same parameters: a window is not a
weight), and per window the page gets the test mAP (`build_dump` + `evaluate`, default
decoding) and the final layer's attention-spread trend (`groups.attention_trends`, the
same detections and criteria as section 4). The weights were trained with their own
window, so a wider one costs mAP; the trend says what the attention does when it is
allowed to spread.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from calibrators import evaluate
from detectors.report.groups import LayerTrend
from detectors.report.model_runs import TrendOptions, passes_and_trends

Log = Callable[[str], None]


@dataclass(frozen=True)
class WindowProbe:
    """One window's measurements: W tokens per side (`metres` wide), test mAP, final-layer
    trend."""

    window: int
    metres: float
    mean_ap: float
    trend: LayerTrend


def probe_windows(weights: Path, windows: Sequence[int], test_seeds: Sequence[int],
                  cache: Path, max_detections: int = 100, trend: TrendOptions | None = None,
                  log: Log | None = None) -> list[WindowProbe]:
    """Run `weights` (a windowed model) with each of `windows` at inference (module
    docstring); the attention passes are cached under `cache / window{W}`."""
    from detectors.dumpwriter import build_dump
    from detectors.model.detector import Detector
    from detectors.registry import load_weights, save_weights

    trend = trend or TrendOptions()
    model, meta = load_weights(weights)
    cfg = model.config
    if cfg.attn_window == 0:
        raise ValueError(f"--probe-windows needs a model with windowed attention; {weights} "
                         f"attends to every token (attn_window 0)")
    out = []
    for w in windows:
        if log is not None:
            log(f"report-v2: window probe {w} x {w}")
        wide = Detector(replace(cfg, attn_window=int(w)))
        wide.load_state_dict(model.state_dict())
        wide.eval()
        folder = Path(cache) / f"window{w}"
        path = save_weights(wide, folder / "weights.pt", meta)   # the cache keys on a file
        trends, _ = passes_and_trends(cfg, path, test_seeds, folder, max_detections, trend)
        mean_ap = evaluate(build_dump(wide, list(test_seeds))).mean_ap
        out.append(WindowProbe(window=int(w), metres=float(w * wide.token_grid.cell),
                               mean_ap=mean_ap, trend=trends[-1]))
    return out


def probe_table(own: int, own_ap: float, own_trend: LayerTrend, probes: Sequence[WindowProbe],
                cell: float) -> str:
    """Markdown: one row per window (the trained one first), with the distance medians."""
    rows = [(own, own * cell, own_ap, own_trend, " (trained)"),
            *[(p.window, p.metres, p.mean_ap, p.trend, "") for p in probes]]
    head = ("| window | mAP (test) | cars, score ≥ 0.8 | ρ vs IoU (≤ −0.6) | "
            "ρ vs distance (≥ 0.6) | rank-deficient C_K | AS median by distance (m⁴): "
            "0-10 / 10-20 / 20-30 / 30-40 / 40-50 m |\n|---|---:|---:|---:|---:|---:|---|")
    lines = [head]
    for w, metres, ap, t, note in rows:
        med = " / ".join("-" if n < 5 else f"{m:.3g}" for n, m in
                         zip(t.stats.vs_distance.n[:5], t.stats.vs_distance.median[:5],
                             strict=True))
        lines.append(f"| {w} x {w} ({metres:g} m){note} | {ap:.3f} | {t.stats.n_detections} | "
                     f"{_rho(t.rho_iou)} | {_rho(t.rho_distance)} | "
                     f"{100 * t.rank_deficient:.1f} % | {med} |")
    return "\n".join(lines)


def _rho(value: float) -> str:
    return "-" if value != value else f"{value:.2f}"
