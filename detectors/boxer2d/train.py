"""Resumable, deterministic training of the image-plane detector (CPU by default).

`train_boxer2d(cfg)` streams frames of `SPLITS["train"]` rendered on the fly by a loader
worker (`data.TrainFrames`: sample i is scene i, so the data of step k depends only on
(seed, k)), optimises `Boxer2DCriterion` with AdamW under the other detectors' schedule
(`detectors.train.learning_rate`: linear warm-up, cosine decay), and

- checkpoints every `ckpt_every` steps to `{run_dir}/ckpt.pt` (model, optimiser, RNG, step)
  and resumes from it automatically (default run dir `runs/boxer2d/`, gitignored);
- appends one row per step to `{run_dir}/log.csv` (`LOG_FIELDS`);
- at the end writes the shipped weights (`weights.WEIGHTS_FILE` unless told otherwise).
"""

from __future__ import annotations

import csv
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from detectors.boxer2d.config import Boxer2DConfig
from detectors.boxer2d.criterion import LOG_TERMS, Boxer2DCriterion
from detectors.boxer2d.data import TrainFrames, collate_frames
from detectors.boxer2d.model import Boxer2D
from detectors.boxer2d.weights import WEIGHTS_FILE, default_config, save_boxer2d
from detectors.train import learning_rate, truncate_log

LOG_FIELDS = ("step", "lr", *LOG_TERMS, "sec_per_step", "elapsed_s")
# Rare-class over-sampling (mean extra objects per training scene), as the lidar recipe.
EXTRA_OBJECTS = {"truck": 1.0, "bus": 2.0, "trailer": 2.0, "construction_vehicle": 2.0,
                 "motorcycle": 2.0, "bicycle": 2.0}


@dataclass(frozen=True)
class Boxer2DTrainConfig:
    """Hyper-parameters of one run; `batch_size` counts frames (six images each)."""

    steps: int = 7000
    batch_size: int = 2
    lr: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    warmup: int = 200
    min_lr_ratio: float = 0.02
    grad_clip: float = 1.0
    extra_objects: dict[str, float] | None = None
    extra_fade: float = 0.125        # the last fraction of the steps without over-sampling
    ckpt_every: int = 200
    threads: int = 2
    workers: int = 1

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "ckpt_every", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")

    @classmethod
    def recipe(cls, **overrides: Any) -> Boxer2DTrainConfig:
        """The shipped recipe (rare-class over-sampling on), with `overrides` not None."""
        return replace(cls(extra_objects=dict(EXTRA_OBJECTS)),
                       **{k: v for k, v in overrides.items() if v is not None})


def train_boxer2d(cfg: Boxer2DTrainConfig, run_dir: str | Path = "runs/boxer2d",
                  weights_out: str | Path | None = WEIGHTS_FILE,
                  model_config: Boxer2DConfig | None = None,
                  stop_after: int | None = None) -> Path | None:
    """Train (or resume) and return the weights written at the end (None when `stop_after`
    steps end the call first, or `weights_out` is None)."""
    from detectors.sim import SPLITS

    torch.set_num_threads(cfg.threads)
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    ckpt_path, log_path = run / "ckpt.pt", run / "log.csv"
    torch.manual_seed(cfg.seed)
    model = Boxer2D(model_config or default_config()).train()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    step, elapsed = 0, 0.0
    if ckpt_path.exists():
        step, elapsed = _resume(ckpt_path, cfg, model, opt)
        truncate_log(log_path, step, LOG_FIELDS)
    elif log_path.exists():
        log_path.unlink()
    fade = cfg.steps - int(round(cfg.extra_fade * cfg.steps))
    data = TrainFrames(model.config, SPLITS["train"], cfg.seed, cfg.extra_objects,
                       extra_until=fade * cfg.batch_size)
    loader = torch.utils.data.DataLoader(
        data, batch_size=cfg.batch_size, collate_fn=collate_frames,
        sampler=range(step * cfg.batch_size, cfg.steps * cfg.batch_size),
        num_workers=cfg.workers, worker_init_fn=_worker_init,
        prefetch_factor=4 if cfg.workers else None)
    criterion = Boxer2DCriterion()
    new_log = not log_path.exists()
    with log_path.open("a", newline="") as log_file:
        writer = csv.DictWriter(log_file, fieldnames=LOG_FIELDS)
        if new_log:
            writer.writeheader()
        t_last = time.perf_counter()
        for images, targets in loader:
            lr = learning_rate(cfg, step)
            for group in opt.param_groups:
                group["lr"] = lr
            losses = criterion(model(images), targets)
            opt.zero_grad(set_to_none=True)
            losses["loss"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            step += 1
            now = time.perf_counter()
            dt, t_last = now - t_last, now
            elapsed += dt
            writer.writerow({"step": step, "lr": f"{lr:.6g}", "sec_per_step": f"{dt:.3f}",
                             "elapsed_s": f"{elapsed:.1f}",
                             **{k: f"{float(v.detach()):.5f}" for k, v in losses.items()}})
            if step % 20 == 0:
                log_file.flush()
            if step % cfg.ckpt_every == 0 or step == cfg.steps:
                log_file.flush()
                _save_checkpoint(ckpt_path, model, opt, step, cfg, elapsed)
            if stop_after is not None and step >= stop_after and step < cfg.steps:
                return None
    if step < cfg.steps or weights_out is None:
        return None
    meta = {"train_config": asdict(cfg), "steps": step, "wall_s": round(elapsed, 1),
            "final_losses": _recent_losses(log_path),
            "command": f"python -m detectors.boxer2d train --steps {cfg.steps} "
                       f"--seed {cfg.seed}"}
    return save_boxer2d(model.eval(), weights_out, meta)


def _worker_init(_: int) -> None:
    # One thread, normal priority: the lidar recipe's nice-19 worker starved whenever other
    # jobs filled the shared cores, and each step then waited ~7 s for its two frames.
    torch.set_num_threads(1)


def _save_checkpoint(path: Path, model: Boxer2D, opt: torch.optim.Optimizer, step: int,
                     cfg: Boxer2DTrainConfig, elapsed: float) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                "train_config": asdict(cfg), "model_config": model.config.to_dict(),
                "elapsed_s": elapsed, "torch_rng": torch.get_rng_state()}, tmp)
    tmp.replace(path)


def _resume(path: Path, cfg: Boxer2DTrainConfig, model: Boxer2D,
            opt: torch.optim.Optimizer) -> tuple[int, float]:
    """Load a checkpoint of the same run -> (its step, its elapsed seconds)."""
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    saved = ckpt["train_config"]
    same = {k: saved.get(k) == v for k, v in asdict(cfg).items()
            if k not in ("ckpt_every", "threads", "workers")}
    if not all(same.values()) or ckpt["model_config"] != model.config.to_dict():
        differ = sorted(k for k, ok in same.items() if not ok)
        raise ValueError(f"{path} belongs to another run (differs in {differ or 'model'}); "
                         "use another run directory or delete it")
    model.load_state_dict(ckpt["model"])
    opt.load_state_dict(ckpt["optimizer"])
    torch.set_rng_state(ckpt["torch_rng"])
    return int(ckpt["step"]), float(ckpt["elapsed_s"])


def _recent_losses(log: Path, n: int = 100) -> dict[str, float]:
    with log.open() as f:
        rows = list(csv.DictReader(f))[-n:]
    return {k: round(float(np.mean([float(r[k]) for r in rows])), 5) for k in LOG_TERMS}
