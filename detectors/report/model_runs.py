"""Everything `detcal report-v2` measures of one weights file (issue 13, item 4).

`run_model` runs one detector over the first test (and optionally val) scenes and keeps:

- `test`: the dump `detcal dump --split test --frames N` writes (`build_dump` with the
  command's defaults: top-K (query, class) pairs with class-wise circle NMS, `layers`
  covariance, devkit ground truth) and `evaluation = calibrators.evaluate(test)`, what
  `detcal evaluate` prints;
  `query_evaluation`: the same with one detection per query (`--decode query`);
- `outputs`: `groups.collect_outputs` over the same scenes (the `max_detections` best
  queries per frame; `group_boxes [N, L, G, 9]` for a group-head model, else None);
- `trends`: `groups.attention_trends` of the report runner's vanilla passes (top
  `max_detections` queries, raw C_K `[N, L, 2, 2]` of every layer; cached per role);
- `val`: the val dump (same writer and defaults) when val seeds are given (section 5).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calibrators import Dump, EvaluationReport, evaluate
from detectors.report.groups import GroupOutputs, LayerTrend, attention_trends, collect_outputs
from detectors.report.runner import MethodSpec, file_digest, run_split

Log = Callable[[str], None]


@dataclass(frozen=True)
class TrendOptions:
    """Which detections enter seed 000's trend test: `class_name` with raw score >=
    `min_score` (the issue: car, 0.8)."""

    class_name: str = "car"
    min_score: float = 0.8


@dataclass(frozen=True)
class ModelRun:
    """One weights file's measurements (module docstring); `sha256` of the file's bytes."""

    role: str
    path: Path
    sha256: str
    head: str
    token_stride: int
    steps: int | None
    test: Dump
    evaluation: EvaluationReport
    query_evaluation: EvaluationReport
    outputs: GroupOutputs
    trends: list[LayerTrend]
    n_attention_frames: int
    token_cell: float
    val: Dump | None = None
    attn_window: int = 0


def run_model(role: str, path: Path, test_seeds: Sequence[int], val_seeds: Sequence[int],
              cache: Path, max_detections: int = 100, trend: TrendOptions = TrendOptions(),
              log: Log | None = None) -> ModelRun:
    """Measure weights file `path` on `test_seeds` (and dump `val_seeds` if any); the
    attention passes are cached under `cache / role`."""
    from detectors.dumpwriter import build_dump
    from detectors.registry import load_weights
    say = log or (lambda _: None)
    model, meta = load_weights(path)
    cfg = model.config
    say(f"report-v2: {role} ({path}): test dump of {len(test_seeds)} scenes")
    test = build_dump(model, list(test_seeds))
    evaluation = evaluate(test)
    query_evaluation = evaluate(build_dump(model, list(test_seeds), decode="query"))
    say(f"report-v2: {role}: per-layer outputs")
    outputs = collect_outputs(model, list(test_seeds), max_detections=max_detections)
    say(f"report-v2: {role}: attention passes")
    trends, vanilla = passes_and_trends(cfg, Path(path), test_seeds, Path(cache) / role,
                                        max_detections, trend)
    val = None
    if val_seeds:
        say(f"report-v2: {role}: val dump of {len(val_seeds)} scenes")
        val = build_dump(model, list(val_seeds))
    steps = meta.get("steps")
    return ModelRun(role=role, path=Path(path), sha256=file_digest(Path(path)), head=cfg.head,
                    token_stride=int(cfg.token_stride),
                    steps=int(steps) if steps is not None else None, test=test,
                    evaluation=evaluation, query_evaluation=query_evaluation,
                    outputs=outputs, trends=trends,
                    n_attention_frames=vanilla.n_frames,
                    token_cell=float(vanilla.token_cell), val=val,
                    attn_window=int(cfg.attn_window))


def passes_and_trends(cfg: Any, path: Path, seeds: Sequence[int], cache: Path,
                      max_detections: int, trend: TrendOptions) -> tuple[list[LayerTrend], Any]:
    """The report runner's (cached) vanilla passes of weights file `path` over `seeds` and
    their attention trends per layer -> (trends, passes)."""
    from detectors.report.dumps import vanilla_dump

    truth, passes = run_split(cfg.sensor, list(seeds), [MethodSpec("vanilla", (path,), 1)],
                              cache, "test", max_detections)
    vanilla = passes["vanilla"]
    trends = attention_trends(vanilla_dump(vanilla, truth, tuple(cfg.classes)),
                              vanilla.attn_cov, vanilla.token_cell, trend.class_name,
                              trend.min_score)
    return trends, vanilla
