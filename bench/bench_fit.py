"""Benchmark: fit T and per-class k on 1M synthetic detections, against netcal's temperature fit,
over a sweep of true temperatures and logit scales; the figure is the WORST ratio.

Ours: `TemperatureScaler.fit` + `DepthScaler.fit` (T and all 10 per-class k plus the pooled
k, 2-D covariances). Reference: netcal's `TemperatureScaling` (method "mle", float64 input)
fitting T alone on the same detections, given as netcal expects them: probabilities
(softmax mode) or the predicted class's confidence in detection mode (sigmoid mode; ours then
gets the same information, the predicted class's logit `[N, 1]`). The sweep: true T in
`T_SWEEP` at the logits' scale 3, and T = 1.5 at scales 0.3 and 30 (labels are drawn at the
true T from the scaled logits, so each row is a consistent data set).

    .bench-venv/bin/python -m bench.bench_fit          # with the reference (see below)
    .venv/bin/python -m bench.bench_fit --n 20000      # quick run; reference skipped if absent

The reference lives only in the benchmark's environment (bench/requirements-reference.txt):
    python3 -m venv .bench-venv
    .bench-venv/bin/pip install -c constraints.txt -e . -r bench/requirements-reference.txt
(the constraints pin the CPU build of torch that netcal pulls in).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import expit, softmax

from calibrators.covariance import DepthScaler
from calibrators.scores import TemperatureScaler

N_CLASSES = 10
T_TRUE = 1.5
T_SWEEP = (0.3, 0.6, 1.0, 1.5, 2.7, 5.0)
#: (true T, logit scale) of every row: the T sweep at scale 3, then the scale sweep.
CASES = tuple((t, 3.0) for t in T_SWEEP) + ((1.5, 0.3), (1.5, 30.0))
K_TRUE = np.linspace(0.01, 0.3, N_CLASSES)


@dataclass
class Data:
    """Synthetic detections: logits, labels, residuals [N, 2], Σ [N, 2, 2], d [N], classes."""

    mode: str
    logits: np.ndarray
    labels: np.ndarray
    residuals: np.ndarray
    covariances: np.ndarray
    distances: np.ndarray
    classes: np.ndarray


@dataclass
class Row:
    """Figures of one score mode: our T, our times (T + k, T alone, k alone), netcal's."""

    mode: str
    t_true: float
    scale: float
    ours_t: float
    ours_s: float
    ours_t_only_s: float
    ours_k_only_s: float
    ref_t: float | None
    ref_s: float | None


def make_data(mode: str, n: int, seed: int, t_true: float = T_TRUE, scale: float = 3.0
              ) -> Data:
    """Seeded detections with labels drawn at `t_true` from logits of std `scale` and
    residuals ~ N(0, Σ + k_c d I). Sigmoid logits are the predicted class's, `[N, 1]`."""
    rng = np.random.default_rng(seed)
    width = N_CLASSES + (1 if mode == "softmax" else 0)
    z = rng.normal(0.0, scale, size=(n, width))
    classes = z[:, :N_CLASSES].argmax(axis=1)
    if mode == "softmax":
        cdf = np.cumsum(softmax(z / t_true, axis=1), axis=1)
        labels = np.minimum((rng.random(n)[:, None] > cdf).sum(axis=1), width - 1)
    else:
        z = z.max(axis=1, keepdims=True)
        labels = (rng.random(n) < expit(z[:, 0] / t_true)).astype(np.int64)
    d = rng.uniform(1.0, 60.0, size=n)
    a = rng.normal(0.0, 0.5, size=(n, 2, 2))
    cov = a @ np.swapaxes(a, 1, 2)
    full = cov + (K_TRUE[classes] * d)[:, None, None] * np.eye(2)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(full), rng.normal(size=(n, 2)))
    return Data(mode, z, labels, r, cov, d, classes)


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    """Median wall time of `repeat` calls and the last result."""
    times, out = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def fit_ours(data: Data) -> tuple[float, float]:
    """Fit T then all per-class k; returns T and the pooled k (the result is what counts)."""
    t = TemperatureScaler(mode=data.mode).fit(data.logits, data.labels).temperature_
    depth = DepthScaler().fit(data.residuals, data.covariances, data.distances, data.classes)
    return t, depth.pooled_k_


def reference_input(data: Data) -> tuple[np.ndarray, np.ndarray, bool]:
    """netcal's input: confidences (float64), labels, and whether detection mode is used."""
    if data.mode == "softmax":
        return softmax(data.logits, axis=1), data.labels, False
    return expit(data.logits), data.labels.astype(np.float64), True


def fit_reference(x: np.ndarray, y: np.ndarray, detection: bool) -> float:
    """netcal TemperatureScaling (method "mle"); netcal's weight is 1 / T."""
    from netcal.scaling import TemperatureScaling

    model = TemperatureScaling(method="mle", detection=detection, use_cuda=False)
    model.fit(x, y, tensorboard=False)
    return 1.0 / float(np.asarray(model.weights).reshape(-1)[0])


def reference_available() -> str | None:
    """None if netcal imports, else why not."""
    try:
        import netcal.scaling  # noqa: F401
        import torch
    except ImportError as exc:
        return f"netcal is not importable ({exc}); install bench/requirements-reference.txt"
    torch.set_num_threads(1)  # a fair single-core comparison on a shared machine
    return None


def run_case(mode: str, t_true: float, scale: float, n: int, seed: int, repeat: int,
             with_reference: bool) -> Row:
    data = make_data(mode, n, seed, t_true, scale)
    ours_s, (ours_t, _) = timed(lambda: fit_ours(data), repeat)
    t_only_s, _ = timed(lambda: TemperatureScaler(mode=mode).fit(data.logits, data.labels),
                        repeat)
    k_only_s, _ = timed(lambda: DepthScaler().fit(data.residuals, data.covariances,
                                                  data.distances, data.classes), repeat)
    ref_t = ref_s = None
    if with_reference:
        x, y, detection = reference_input(data)
        ref_s, ref_t = timed(lambda: fit_reference(x, y, detection), 1)
    return Row(mode, t_true, scale, ours_t, ours_s, t_only_s, k_only_s, ref_t, ref_s)


def table(rows: list[Row], n: int) -> str:
    """Markdown: the worst ratios per mode, then every row (reference columns n/a when it
    was skipped)."""
    lines = [f"T and per-class depth k on {n:,} synthetic detections ({N_CLASSES} classes, "
             "2-D covariances) for true T in " + ", ".join(f"{t:g}" for t in T_SWEEP)
             + " (logit std 3) and T = 1.5 at logit std 0.3 and 30; reference: netcal "
             "`TemperatureScaling(method=\"mle\")` on float64 input, T only, torch on 1 "
             "thread (sigmoid: both get the predicted class's logit / confidence `[N, 1]`); "
             "ours: median of repeated runs. Ratios are netcal's time over ours.", ""]
    if all(r.ref_s is not None for r in rows):
        lines += ["| score mode | worst netcal / ours T | worst netcal / ours k | "
                  "worst netcal / ours T + k | largest T gap |", "|---|---|---|---|---|"]
        for mode in dict.fromkeys(r.mode for r in rows):
            mine = [r for r in rows if r.mode == mode]
            worst = [min(mine, key=lambda r, f=f: r.ref_s / f(r)) for f in
                     (lambda r: r.ours_t_only_s, lambda r: r.ours_k_only_s,
                      lambda r: r.ours_s)]
            cells = [f"{r.ref_s / f(r):.1f}x (T = {r.t_true:g}, std {r.scale:g})"
                     for r, f in zip(worst, (lambda r: r.ours_t_only_s,
                                             lambda r: r.ours_k_only_s,
                                             lambda r: r.ours_s), strict=True)]
            gap = max(abs(r.ours_t - r.ref_t) / r.ref_t for r in mine)
            lines.append(f"| {mode} | " + " | ".join(cells) + f" | {100 * gap:.4f} % |")
        lines.append("")
        for mode in dict.fromkeys(r.mode for r in rows):
            worst = min((r for r in rows if r.mode == mode),
                        key=lambda r: r.ref_s / r.ours_t_only_s)
            if worst.ref_s < 10 * worst.ours_t_only_s:
                lines += [f"{mode}: below the 10x target at T = {worst.t_true:g}, logit std "
                          f"{worst.scale:g}: netcal's fit is at its fastest there "
                          f"({worst.ref_s:.3f} s; weakly informative or saturated logits let "
                          f"its optimiser stop early), ours takes {worst.ours_t_only_s:.3f} s.",
                          ""]
    lines += ["| score mode | true T | logit std | ours T + k (s) | ours T (s) | ours k (s) "
              "| netcal T (s) | netcal / ours T | netcal / ours T + k | T ours | T netcal "
              "| T gap |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = [r.mode, f"{r.t_true:g}", f"{r.scale:g}", f"{r.ours_s:.3f}",
                 f"{r.ours_t_only_s:.3f}", f"{r.ours_k_only_s:.3f}"]
        if r.ref_s is None:
            cells += ["n/a", "n/a", "n/a", f"{r.ours_t:.6f}", "n/a", "n/a"]
        else:
            gap = abs(r.ours_t - r.ref_t) / r.ref_t
            cells += [f"{r.ref_s:.3f}", f"{r.ref_s / r.ours_t_only_s:.1f}x",
                      f"{r.ref_s / r.ours_s:.1f}x", f"{r.ours_t:.6f}", f"{r.ref_t:.6f}",
                      f"{100 * gap:.4f} %"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines).rstrip()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1_000_000, help="detections per score mode")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3, help="timings of ours (median)")
    parser.add_argument("--no-write", action="store_true", help="do not touch docs/")
    args = parser.parse_args(argv)

    why_not = reference_available()
    if why_not:
        print(f"reference skipped: {why_not}")
    rows = []
    for mode in ("softmax", "sigmoid"):
        for t_true, scale in CASES:
            row = run_case(mode, t_true, scale, args.n, args.seed, args.repeat, why_not is None)
            rows.append(row)
            ref = "" if row.ref_s is None else \
                f"; netcal T only {row.ref_s:.3f} s, T = {row.ref_t:.6f}, " \
                f"ratio T {row.ref_s / row.ours_t_only_s:.1f}x, T + k " \
                f"{row.ref_s / row.ours_s:.1f}x"
            print(f"{mode} T={t_true:g} std={scale:g}: ours T + k {row.ours_s:.3f} s (T only "
                  f"{row.ours_t_only_s:.3f} s, k only {row.ours_k_only_s:.3f} s), "
                  f"T = {row.ours_t:.6f}{ref}", flush=True)
    markdown = table(rows, args.n)
    print(markdown)
    if not args.no_write and why_not is None:
        from bench._report import write_section

        write_section("fit", markdown)


if __name__ == "__main__":
    main()
