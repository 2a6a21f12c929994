"""Per-frame forward time of each bundled detector on the CPU: 2 threads, batch 1.

For every sensor whose shipped weights exist, the detector runs on fixed test-split scenes
(`detectors.sim.SPLITS["test"]`); the median over `--repeat` timed passes (after warm-up)
is reported with the frame's number of points and queries, and the same with the default
decoding (`detectors.infer.postprocess`: top-K pairs and circle NMS) after the forward
pass, what `detcal dump` and `/v1/detect` run per frame. Reference: the thesis's 50 ms
per frame (on a GPU), which is also the lidar detector's target on 2 CPU cores;
the ratio column is time / 50 ms (below 1 meets the target).

The image-plane detector (`detectors.boxer2d`) is timed the same way on a six-camera frame
(the six images as one batch, their tensors built outside the timed call), with and without
its decoding (`decode_image`: top-100 pairs per image and their per-layer boxes); its target
is the same 50 ms per frame.

Run: `.venv/bin/python -m bench.bench_detectors` (writes the "detectors" section of
docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from detectors.model.detector import Detector

REFERENCE_MS = 50.0


def time_forward(model: Detector, points: torch.Tensor, repeat: int,
                 warmup: int = 3, decode: bool = False) -> float:
    """Median wall time in ms of `model([points])` under inference mode (followed by the
    default decoding when `decode`)."""
    from detectors.infer import postprocess
    from detectors.vocab import DECODINGS

    classes = model.config.classes

    def run() -> None:
        out = model([points])
        if decode:
            postprocess(out, max_detections=model.config.n_queries, decode=DECODINGS[0],
                        classes=classes)

    return median_ms(run, repeat, warmup)


def median_ms(run: Callable[[], object], repeat: int, warmup: int) -> float:
    """Median wall time in ms of `repeat` calls of `run()` under inference mode, after
    `warmup` untimed ones."""
    with torch.inference_mode():
        for _ in range(warmup):
            run()
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            run()
            times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--scenes", type=int, default=3, help="test scenes per sensor")
    parser.add_argument("--no-write", action="store_true", help="do not touch the docs")
    parser.add_argument("--weights", action="append", default=[], metavar="SENSOR=PATH",
                        help="time the weights file PATH for SENSOR (a candidate before it "
                             "ships) beside the shipped ones; repeatable")
    args = parser.parse_args(argv)
    candidates = dict(_candidate(text) for text in args.weights)

    from bench._report import write_section
    from detectors.registry import build_detector, sensor_names, weights_path
    from detectors.sim import SPLITS, make_frame

    torch.set_num_threads(2)
    rows, skipped = [], []
    for sensor in sensor_names():
        if not weights_path(sensor).exists():
            skipped.append(sensor)
            print(f"{sensor}: skipped (no weights at {weights_path(sensor)})")
            continue
        files = [(sensor, None)] + ([(f"{sensor} (candidate {candidates[sensor]})",
                                      candidates[sensor])] if sensor in candidates else [])
        for label, path in files:
            model = build_detector(sensor, weights=path)
            seeds = list(SPLITS["test"])[:args.scenes]
            ms, ms_dec, n_points = [], [], []
            for seed in seeds:
                pts = np.array(make_frame(seed, sensor).sensor_frame.points, dtype=np.float32)
                n_points.append(len(pts))
                ms.append(time_forward(model, torch.from_numpy(pts), args.repeat))
                ms_dec.append(time_forward(model, torch.from_numpy(pts), args.repeat,
                                           decode=True))
            t, t_dec = statistics.median(ms), statistics.median(ms_dec)
            rows.append((label, int(np.mean(n_points)), model.config.n_queries, t, t_dec))
            print(f"{label}: {t:.1f} ms/frame (median of {len(seeds)} scenes x {args.repeat}), "
                  f"{t_dec:.1f} ms with decoding, "
                  f"{int(np.mean(n_points))} points, {model.config.n_queries} queries, "
                  f"ratio to {REFERENCE_MS:.0f} ms reference {t / REFERENCE_MS:.2f}")

    image_row = _time_boxer2d(args.scenes, args.repeat)
    if image_row is None:
        skipped.append("boxer2d")
    else:
        rows.append(image_row)

    lines = ["## Detectors: forward time per frame (CPU, 2 threads, batch 1)", "",
             "Median over test-split scenes of `model([points])` under `torch.inference_mode`; "
             f"reference: {REFERENCE_MS:.0f} ms per frame (thesis, GPU; the lidar target).", "",
             "boxer2d: a six-camera frame of 120 x 71 RGB + depth images, batch of 6, queries "
             "per image; decoding: the top-100 pairs per image.", "",
             "| sensor | points/frame | queries | ms/frame | ratio to 50 ms | ms/frame with "
             "decoding (top-K + circle NMS) |",
             "|---|---:|---:|---:|---:|---:|"]
    lines += [f"| {s} | {p} | {q} | {t:.1f} | {t / REFERENCE_MS:.2f} | {td:.1f} |"
              for s, p, q, t, td in rows]
    if skipped:
        lines += ["", f"Skipped (no shipped weights yet): {', '.join(skipped)}."]
    if not args.no_write:
        write_section("detectors", "\n".join(lines))


def _time_boxer2d(scenes: int, repeat: int, warmup: int = 3
                  ) -> tuple[str, str, int, float, float] | None:
    """The boxer2d row (label, pixels per frame, queries per image, ms, ms with decoding):
    medians over `scenes` test frames of `repeat` timed passes; None without its weights."""
    from detectors.boxer2d import build_boxer2d, decode_image, frame_inputs
    from detectors.boxer2d.weights import WEIGHTS_FILE
    from detectors.sim import SPLITS, make_image_frame

    if not WEIGHTS_FILE.exists():
        print(f"boxer2d: skipped (no weights at {WEIGHTS_FILE})")
        return None
    model = build_boxer2d()
    ms, ms_dec = [], []
    for seed in list(SPLITS["test"])[:scenes]:
        inputs = frame_inputs(make_image_frame(seed).images, model.config)
        for decode, out in ((False, ms), (True, ms_dec)):
            def run(decode: bool = decode, inputs: torch.Tensor = inputs) -> None:
                result = model(inputs)
                if decode:
                    for i in range(inputs.shape[0]):
                        decode_image(result, i, model.config)
            out.append(median_ms(run, repeat, warmup))
    t, t_dec = statistics.median(ms), statistics.median(ms_dec)
    print(f"boxer2d: {t:.1f} ms/frame (six cameras), {t_dec:.1f} ms with decoding, ratio to "
          f"{REFERENCE_MS:.0f} ms reference {t / REFERENCE_MS:.2f}")
    return ("boxer2d (six cameras)", "6 x 120 x 71 px", model.config.n_queries, t, t_dec)


def _candidate(text: str) -> tuple[str, Path]:
    sensor, sep, path = text.partition("=")
    if not sep or not Path(path).is_file():
        raise SystemExit(f"--weights must be SENSOR=PATH of an existing file, got {text!r}")
    return sensor, Path(path)


if __name__ == "__main__":
    main()
