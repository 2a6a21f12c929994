"""Resumable, deterministic training of one sensor's detector (CPU; a GPU where there is one).

`train(sensor)` streams augmented frames of `detectors.sim.SPLITS["train"]` (generated on the
fly by a loader worker), optimises `detectors.losses.SetCriterion` with AdamW under a linear
warm-up + cosine schedule, and

- checkpoints every `ckpt_every` steps to `runs/{sensor}/ckpt.pt` (model, optimiser, RNG,
  step) and resumes from it automatically: the data of step k depends only on (seed, k), so
  an interrupted run continues exactly where it stopped;
- appends one row per step to `runs/{sensor}/log.csv`;
- at the end writes the shipped weights `detectors/weights/{sensor}.pt` (float32 state
  dict + config + training metadata).

`TrainConfig.device` ("cpu" by default, the recipes' budget machine) may name a torch device
such as "cuda": the frames are still simulated on the CPU by the loader workers, the model,
its batches and the loss run on the device. The data of step k is the same on any device;
the arithmetic is not bit-identical across devices, and a checkpoint resumes on any device.
"""

from __future__ import annotations

import csv
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from detectors.losses import SetCriterion, Target
from detectors.model.detector import Detector, DetectorConfig
from detectors.registry import (
    SUB_ENSEMBLE_RECIPE,
    TRAIN_RECIPES,
    build_detector,
    save_weights,
    weights_path,
)
from detectors.samples import TrainSamples, collate
from detectors.subensemble import attach_trunk, train_mode

LOG_FIELDS = ("step", "lr", "loss", "heatmap", "cls", "box", "cls_last", "box_last",
              "sec_per_step", "elapsed_s")


@dataclass(frozen=True)
class TrainConfig:
    """Hyper-parameters of one training run (build it with `for_sensor`)."""

    sensor: str
    # Set by the sensor's recipe, detectors.registry.TRAIN_RECIPES (the only place with
    # their values).
    steps: int
    batch_size: int
    lr: float
    weight_decay: float
    seed: int
    # Schedule: linear warm-up steps, cosine floor as a fraction of lr, gradient-norm clip.
    warmup: int = 200
    min_lr_ratio: float = 0.02
    grad_clip: float = 10.0
    # Mean extra objects per class and training scene (rare-class over-sampling, see
    # detectors.sim.traffic.place_extra); None trains on the world's own class frequencies.
    extra_objects: dict[str, float] | None = None
    # Fade-out (seed 001, Sec. III-F): the last `extra_fade` fraction of the steps trains
    # without the object sampling, on the world's own class frequencies.
    extra_fade: float = 0.0
    # Every simulated scene serves this many samples, each augmented anew (see
    # detectors.samples.TrainSamples: the simulation is a third of a lidar step's CPU time).
    scene_reuse: int = 1
    # Deep sub-ensemble member: copy and freeze the trunk of this weights file, train a
    # fresh decoder head on it (detectors.subensemble). None trains the whole model.
    base_weights: str | None = None
    # Running: checkpoint every N steps, torch threads, frame-generating worker processes.
    ckpt_every: int = 200
    # Also keep the weights at every N-th step as `{run_dir}/step_{N}.pt` (0: none), to
    # follow a quantity (an attention trend, mAP) through one run.
    snapshot_every: int = 0
    threads: int = 2
    workers: int = 1
    device: str = "cpu"

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "threads", "ckpt_every", "scene_reuse"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.workers < 0 or self.warmup < 0 or self.snapshot_every < 0:
            raise ValueError(f"workers, warmup and snapshot_every must be >= 0, got "
                             f"{self.workers}, {self.warmup}, {self.snapshot_every}")
        if not 0.0 <= self.extra_fade <= 1.0:
            raise ValueError(f"extra_fade must be in [0, 1], got {self.extra_fade}")
        try:
            torch.device(self.device)
        except (RuntimeError, TypeError):
            raise ValueError(f"device must be a torch device such as 'cpu' or 'cuda', got "
                             f"{self.device!r}") from None

    @property
    def fade_step(self) -> int:
        """The first step trained without object sampling (`steps` when there is no fade)."""
        return self.steps - int(round(self.extra_fade * self.steps))

    @classmethod
    def for_sensor(cls, sensor: str, **overrides: Any) -> TrainConfig:
        """`sensor`'s recipe (a sub-ensemble head's when `base_weights` is given), with the
        `overrides` that are not None."""
        if sensor not in TRAIN_RECIPES:
            raise ValueError(f"sensor must be one of {list(TRAIN_RECIPES)}, got {sensor!r}")
        recipe = dict(TRAIN_RECIPES[sensor])
        if overrides.get("base_weights") is not None:   # a sub-ensemble head
            recipe.update(SUB_ENSEMBLE_RECIPE)
        base = cls(sensor=sensor, **recipe)
        return replace(base, **{k: v for k, v in overrides.items() if v is not None})


@dataclass(frozen=True)
class TrainResult:
    """Where the run left its files, and how it went."""

    weights: Path | None
    checkpoint: Path
    log: Path
    steps: int
    wall_s: float
    final_losses: dict[str, float]


class Schedule(Protocol):
    """What `learning_rate` reads of a training configuration (TrainConfig has it all)."""

    lr: float
    steps: int
    warmup: int
    min_lr_ratio: float


def learning_rate(cfg: Schedule, step: int) -> float:
    """Linear warm-up over `warmup` steps, then cosine decay to `min_lr_ratio * lr`."""
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    t = (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup)
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def _save_checkpoint(path: Path, model: Detector, opt: torch.optim.Optimizer, step: int,
                     cfg: TrainConfig, elapsed: float) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                "train_config": asdict(cfg), "model_config": model.config.to_dict(),
                "elapsed_s": elapsed,
                "torch_rng": torch.get_rng_state(),
                "numpy_rng": np.random.get_state()}, tmp)
    tmp.replace(path)


def truncate_log(log: Path, step: int, fields: tuple[str, ...] = LOG_FIELDS) -> None:
    """Drop log rows after `step` (written after the checkpoint a resumed run restarts from);
    `fields` are the log's columns."""
    if not log.exists():
        return
    with log.open() as f:
        rows = [r for r in csv.DictReader(f) if int(r["step"]) <= step]
    with log.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


def _recent_losses(log: Path, n: int = 100) -> dict[str, float]:
    if not log.exists():
        return {}
    with log.open() as f:
        rows = list(csv.DictReader(f))[-n:]
    if not rows:
        return {}
    keys = ("loss", "heatmap", "cls", "box", "cls_last", "box_last")
    return {k: float(np.mean([float(r[k]) for r in rows])) for k in keys}


def train(cfg: TrainConfig, run_dir: str | Path | None = None, resume: bool = True,
          weights_out: str | Path | None = None, progress: bool = True,
          on_step: Callable[[int, dict[str, float]], None] | None = None,
          model_config: DetectorConfig | None = None) -> TrainResult:
    """Train (or resume training) `cfg.sensor`'s detector; see the module docstring.

    `model_config` replaces the registry's architecture (tests train tiny models with it).
    """
    from detectors.sim import SPLITS

    torch.set_num_threads(cfg.threads)
    run = Path(run_dir) if run_dir is not None else Path("runs") / cfg.sensor
    run.mkdir(parents=True, exist_ok=True)
    ckpt_path, log_path = run / "ckpt.pt", run / "log.csv"

    model, opt, device = _model_and_optimizer(cfg, model_config)
    start, elapsed = 0, 0.0
    if resume and ckpt_path.exists():
        start, elapsed = _resume(ckpt_path, log_path, cfg, model, opt)
    elif log_path.exists():
        log_path.unlink()
    criterion = SetCriterion(model.fine_grid, len(model.config.classes),
                             class_group=model.class_group)
    stepper = _Stepper(cfg, model, opt, criterion, device)
    loader = _loader(cfg, model, SPLITS["train"], start)

    bar = _progress_bar(cfg, start) if progress else None
    new_log = not log_path.exists()
    log_file = log_path.open("a", newline="")
    writer = csv.DictWriter(log_file, fieldnames=LOG_FIELDS)
    if new_log:
        writer.writeheader()
    try:
        step, elapsed = _run_steps(stepper, loader, run, (log_file, writer), bar, start,
                                   elapsed, on_step)
    finally:
        log_file.close()
        if bar is not None:
            bar.close()

    final = _recent_losses(log_path)
    out = None
    if step >= cfg.steps:
        out = Path(weights_out) if weights_out is not None else weights_path(cfg.sensor)
        _save_final(model, out, cfg, step, elapsed, final)
    return TrainResult(weights=out, checkpoint=ckpt_path, log=log_path, steps=step,
                       wall_s=elapsed, final_losses=final)


@dataclass
class _Stepper:
    """The model, its optimiser and loss on the training device: one step at a time."""

    cfg: TrainConfig
    model: Detector
    opt: torch.optim.Optimizer
    criterion: SetCriterion
    device: torch.device

    def __call__(self, batch: list[Any], step: int) -> tuple[float, dict[str, torch.Tensor]]:
        """One optimisation step on `batch` at the learning rate of `step`: (lr, losses)."""
        lr = learning_rate(self.cfg, step)
        for group in self.opt.param_groups:
            group["lr"] = lr
        device = self.device
        outputs = self.model([s.points.to(device) for s in batch], need_attention=False)
        losses = self.criterion(outputs, [Target(s.target.labels.to(device),
                                                 s.target.boxes.to(device)) for s in batch])
        self.opt.zero_grad(set_to_none=True)
        losses["loss"].backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        self.opt.step()
        return lr, losses


def _model_and_optimizer(cfg: TrainConfig, model_config: DetectorConfig | None
                         ) -> tuple[Detector, torch.optim.Optimizer, torch.device]:
    """A fresh model (seeded by `cfg.seed`; on a frozen trunk with `base_weights`) on
    `cfg.device`, its AdamW optimiser and the device."""
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    model = Detector(model_config) if model_config is not None else \
        build_detector(cfg.sensor, pretrained=False)
    if cfg.base_weights is not None:
        attach_trunk(model, cfg.base_weights)
    device = torch.device(cfg.device)
    model.to(device)
    train_mode(model, frozen_trunk=cfg.base_weights is not None)
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=cfg.lr,
                            weight_decay=cfg.weight_decay)
    return model, opt, device


def _resume(ckpt_path: Path, log_path: Path, cfg: TrainConfig, model: Detector,
            opt: torch.optim.Optimizer) -> tuple[int, float]:
    """Load the checkpoint into `model`, `opt` and the RNGs and drop the log rows after it:
    (its step, its elapsed seconds); ValueError when it is of another run or model."""
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    saved = ckpt["train_config"]
    if saved["seed"] != cfg.seed or saved["batch_size"] != cfg.batch_size or \
            saved.get("extra_objects") != cfg.extra_objects or \
            saved.get("extra_fade", 0.0) != cfg.extra_fade or \
            saved.get("scene_reuse", 1) != cfg.scene_reuse or \
            saved.get("base_weights") != cfg.base_weights:
        raise ValueError(f"{ckpt_path} was trained with another seed, batch size, "
                         "object sampling (or its fade-out), scene reuse or base model; "
                         "start fresh (--fresh) or use another run directory")
    if ckpt.get("model_config", model.config.to_dict()) != model.config.to_dict():
        raise ValueError(f"{ckpt_path} holds another detector architecture (head, token "
                         "stride, widths); start fresh (--fresh) or use another run "
                         "directory")
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as exc:
        raise ValueError(f"{ckpt_path} holds another detector architecture; start fresh "
                         f"(--fresh) or use another run directory ({exc})") from None
    opt.load_state_dict(ckpt["optimizer"])
    torch.set_rng_state(ckpt["torch_rng"])
    np.random.set_state(ckpt["numpy_rng"])
    start, elapsed = int(ckpt["step"]), float(ckpt["elapsed_s"])
    truncate_log(log_path, start)
    return start, elapsed


def _loader(cfg: TrainConfig, model: Detector, split: Any, start: int
            ) -> torch.utils.data.DataLoader:
    """The batches of steps `start ..` of the training `split`."""
    data = TrainSamples(cfg.sensor, split, model.config.features,
                        model.grid.half_extent, seed=cfg.seed,
                        n_samples=cfg.steps * cfg.batch_size,
                        extra_objects=cfg.extra_objects,
                        extra_until=cfg.fade_step * cfg.batch_size,
                        reuse=cfg.scene_reuse)
    sampler = range(start * cfg.batch_size, cfg.steps * cfg.batch_size)
    # With scene reuse, only the first use of a scene is simulated: `span` samples in a row
    # are new scenes, then (reuse - 1) * span are cheap re-augmentations. With two batches
    # of prefetch every step of a run of new scenes waited on the worker (lidar: 0.50-0.85
    # s against 0.36 s); prefetching up to a whole span lets the worker start on the next
    # scenes during the re-augmented steps (with the low-priority worker below: 0.44 ->
    # 0.43 s per step on average). The data of step k is unchanged.
    prefetch = max(2, math.ceil(data.span / cfg.batch_size)) if cfg.scene_reuse > 1 else 2
    return torch.utils.data.DataLoader(
        data, batch_size=cfg.batch_size, sampler=sampler, collate_fn=collate,
        num_workers=cfg.workers, worker_init_fn=_worker_init,
        persistent_workers=False, prefetch_factor=prefetch if cfg.workers else None)


def _progress_bar(cfg: TrainConfig, start: int) -> Any:
    import sys

    from tqdm import tqdm

    return tqdm(total=cfg.steps, initial=start, desc=f"train {cfg.sensor}", unit="step",
                mininterval=0.5 if sys.stderr.isatty() else 30.0)


def _run_steps(stepper: _Stepper, loader: torch.utils.data.DataLoader, run: Path,
               log: tuple[Any, csv.DictWriter], bar: Any, step: int, elapsed: float,
               on_step: Callable[[int, dict[str, float]], None] | None) -> tuple[int, float]:
    """Train on every batch of `loader`, logging, checkpointing and snapshotting as `cfg`
    says: (the last step, the elapsed seconds)."""
    cfg = stepper.cfg
    log_file, writer = log
    t_last = time.perf_counter()
    for batch in loader:
        lr, losses = stepper(batch, step)
        step += 1
        now = time.perf_counter()
        dt, t_last = now - t_last, now
        elapsed += dt
        row = {k: float(v.detach()) for k, v in losses.items()}
        writer.writerow({"step": step, "lr": f"{lr:.6g}", "sec_per_step": f"{dt:.3f}",
                         "elapsed_s": f"{elapsed:.1f}",
                         **{k: f"{v:.5f}" for k, v in row.items()}})
        if on_step is not None:
            on_step(step, row)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{row['loss']:.3f}", cls=f"{row['cls_last']:.3f}",
                            box=f"{row['box_last']:.3f}")
        if step % cfg.ckpt_every == 0 or step == cfg.steps:
            log_file.flush()
            _save_checkpoint(run / "ckpt.pt", stepper.model, stepper.opt, step, cfg, elapsed)
        if cfg.snapshot_every and step % cfg.snapshot_every == 0 and step < cfg.steps:
            save_weights(stepper.model, run / f"step_{step}.pt",
                         {"train_config": asdict(cfg), "steps": step})
    return step, elapsed


def _save_final(model: Detector, out: Path, cfg: TrainConfig, step: int, elapsed: float,
                final: dict[str, float]) -> None:
    """The shipped weights of a finished run, with its training metadata."""
    meta = {"train_config": asdict(cfg), "steps": step, "wall_s": round(elapsed, 1),
            "final_losses": final,
            "command": f"detcal train --sensor {cfg.sensor} --steps {cfg.steps} "
                       f"--seed {cfg.seed}"
                       + (f" --base-weights {cfg.base_weights}" if cfg.base_weights else "")}
    save_weights(model.eval(), out, meta)


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)
    # The training process's two threads run in lock-step parallel regions: a simulating
    # worker that takes a core from one of them stalls both. At the lowest priority the
    # worker mostly runs in the gaps of the training process (its single-threaded parts),
    # prefetching ahead (see `prefetch` in `train`).
    os.nice(19)
