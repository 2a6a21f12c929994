"""Cached forward passes of a sensor's detector(s) over the scenes of one split.

One frame is simulated once and fed to every model that still has to run on it; each
*method*'s passes are cached as one NPZ per (sensor, split, method) under the cache folder, so
a re-run of `detcal report` only redoes what changed. Methods:

- `vanilla`: the report's model (`sensor.report_base`: the shipped one, or the sensor's
  `_de0.pt`) in eval mode; the `max_detections` best queries per frame
  (final-layer score), with the logits and boxes of every decoder layer and the attention
  covariance C_K (seed 000, top-K attention over the token grid) of every layer;
- `mcd`: that model with dropout on (`infer.enable_mc_dropout`), `n_members` passes;
  pass m of scene s runs under `torch.manual_seed(mc_seed(s, m))`, so a pass does not depend
  on the frames before it; all Q queries, final layer only (merged later by query index);
- `de` / `dse`: one weights file per member (DE: member 0 = that model; DSE: the new
  heads), all Q queries, final layer only; sub-ensemble members share its trunk, so
  the trunk runs once per frame and only the decoder heads run per member
  (`Detector.encode` / `decode`).

Shapes in a `Passes` (N rows pooled over frames and members, L' layers kept, C classes):

    member [N] int, frame [N] int (index into the split's seeds), query [N] int,
    layer_logits [N, L', C] float32, layer_boxes [N, L', 9] float32,
    seconds [M] model forward time of each member summed over the frames,
    attn_cov [N, L, 2, 2] float64 | None (vanilla only), token_cell: token cell size (m)

A cache file holds a key (sha256 of the cache version, sensor, split seeds, max_detections,
method and every weights file's bytes); a stale key is recomputed. An MC-dropout cache with
at least the requested number of passes is reused (the first passes are taken).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

CACHE_VERSION = 1
METHODS = ("vanilla", "mcd", "de", "dse")
ATTENTION_TOP_K = 6
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class MethodSpec:
    """What to run: `name` in METHODS, weights files (member m uses `weights[m]`, or
    `weights[0]` for every MC-dropout pass) and the number of members."""

    name: str
    weights: tuple[Path, ...]
    n_members: int

    def __post_init__(self) -> None:
        if self.name not in METHODS:
            raise ValueError(f"method must be one of {list(METHODS)}, got {self.name!r}")
        if self.n_members < 1:
            raise ValueError(f"n_members must be >= 1, got {self.n_members}")
        if self.name != "mcd" and len(self.weights) != self.n_members:
            raise ValueError(f"{self.name} needs one weights file per member: "
                             f"{len(self.weights)} files for {self.n_members} members")


@dataclass(frozen=True)
class Truth:
    """Ground truth of a split's F scenes: seeds [F], frame_ids [F] str, gt_frame [G] int,
    gt_labels [G] int, gt_boxes [G, 9] float64 (devkit rule: a lidar or radar point)."""

    seeds: np.ndarray
    frame_ids: np.ndarray
    gt_frame: np.ndarray
    gt_labels: np.ndarray
    gt_boxes: np.ndarray


@dataclass(frozen=True)
class Passes:
    """One method's cached passes over a split (shapes in the module docstring)."""

    method: str
    n_members: int
    n_frames: int
    member: np.ndarray
    frame: np.ndarray
    query: np.ndarray
    layer_logits: np.ndarray
    layer_boxes: np.ndarray
    seconds: np.ndarray
    token_cell: float
    attn_cov: np.ndarray | None = None
    from_cache: bool = field(default=False, compare=False)

    def first_members(self, n: int) -> Passes:
        """The passes of members `0 .. n-1` only."""
        if not 1 <= n <= self.n_members:
            raise ValueError(f"n must be in [1, {self.n_members}], got {n}")
        keep = self.member < n
        return replace(self, n_members=n, member=self.member[keep], frame=self.frame[keep],
                       query=self.query[keep], layer_logits=self.layer_logits[keep],
                       layer_boxes=self.layer_boxes[keep], seconds=self.seconds[:n],
                       attn_cov=None if self.attn_cov is None else self.attn_cov[keep])

    def forward_ms_per_frame(self) -> float:
        """Model time per frame in ms, all members together (they run one after another)."""
        return 1000.0 * float(np.sum(self.seconds)) / max(self.n_frames, 1)


def mc_seed(scene_seed: int, member: int) -> int:
    """Torch seed of MC-dropout pass `member` on scene `scene_seed`."""
    return (int(scene_seed) * 64 + int(member)) % (2**63 - 1)


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def cache_key(sensor: str, seeds: Sequence[int], max_detections: int, spec: MethodSpec) -> str:
    """Key of one method's cache (the member count of MC dropout is not part of it)."""
    h = hashlib.sha256()
    parts = [f"v{CACHE_VERSION}", sensor, spec.name, str(max_detections),
             ",".join(str(int(s)) for s in seeds)]
    parts += [file_digest(p) for p in spec.weights]
    h.update("|".join(parts).encode())
    return h.hexdigest()


def run_split(sensor: str, seeds: Sequence[int], specs: Sequence[MethodSpec], cache_dir: Path,
              split: str, max_detections: int = 100, progress: Progress | None = None
              ) -> tuple[Truth, dict[str, Passes]]:
    """Ground truth and every method's passes over scenes `seeds`, from the cache if valid.

    Writes `{cache_dir}/{sensor}/{split}_{method}.npz` and `{split}_truth.npz`.
    """
    folder = Path(cache_dir) / sensor
    folder.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError(f"the {split} split needs at least one frame")
    out: dict[str, Passes] = {}
    todo: list[tuple[MethodSpec, str]] = []
    for spec in specs:
        key = cache_key(sensor, seeds, max_detections, spec)
        cached = _load(folder / f"{split}_{spec.name}.npz", key, spec.n_members)
        if cached is None:
            todo.append((spec, key))
        else:
            out[spec.name] = cached
    truth_path = folder / f"{split}_truth.npz"
    truth_key = hashlib.sha256(f"v{CACHE_VERSION}|{sensor}|{seeds}".encode()).hexdigest()
    truth = _load_truth(truth_path, truth_key)
    if todo or truth is None:
        truth, fresh = _compute(sensor, seeds, [s for s, _ in todo], max_detections, split,
                                progress)
        _save_truth(truth_path, truth_key, truth)
        for spec, key in todo:
            _save(folder / f"{split}_{spec.name}.npz", key, fresh[spec.name])
            out[spec.name] = fresh[spec.name]
    return truth, out


def _compute(sensor: str, seeds: list[int], specs: list[MethodSpec], max_detections: int,
             split: str, progress: Progress | None) -> tuple[Truth, dict[str, Passes]]:
    """Simulate every scene once and run every spec's models on it."""
    import torch

    from detectors.dumpwriter import frame_id, visible_gt
    from detectors.sim import make_frame

    models = {spec.name: _models(sensor, spec) for spec in specs}
    rows: dict[str, list[dict[str, np.ndarray]]] = {spec.name: [] for spec in specs}
    seconds = {spec.name: np.zeros(spec.n_members) for spec in specs}
    gt_frame, gt_labels, gt_boxes = [], [], []
    token_cell = 0.0
    for i, seed in enumerate(seeds):
        frame = make_frame(seed, sensor)
        keep = visible_gt(frame, sensor, "lidar_radar")
        boxes = np.asarray(frame.scene.boxes, dtype=np.float64).reshape(-1, 9)[keep]
        gt_boxes.append(boxes)
        gt_labels.append(np.asarray(frame.scene.labels, dtype=np.int64).reshape(-1)[keep])
        gt_frame.append(np.full(len(boxes), i, dtype=np.int64))
        points = torch.from_numpy(np.array(frame.sensor_frame.points, dtype=np.float32))
        for spec in specs:
            encoded = None
            if spec.name == "dse":   # members share the trunk: one encode serves all heads
                with torch.no_grad():
                    start = time.perf_counter()
                    encoded = models["dse"][0].encode([points])
                    seconds["dse"][0] += time.perf_counter() - start
            for m in range(spec.n_members):
                model = models[spec.name][0 if spec.name == "mcd" else m]
                token_cell = float(model.token_grid.cell)
                if spec.name == "mcd":
                    torch.manual_seed(mc_seed(seed, m))
                with torch.no_grad():
                    start = time.perf_counter()
                    outputs = model([points]) if encoded is None else model.decode(encoded)
                    seconds[spec.name][m] += time.perf_counter() - start
                rows[spec.name].append(_keep(outputs, model, spec.name, max_detections, i, m))
        if progress is not None:
            progress(split, i + 1, len(seeds))
    truth = Truth(seeds=np.asarray(seeds, dtype=np.int64),
                  frame_ids=np.array([frame_id(s) for s in seeds]),
                  gt_frame=np.concatenate(gt_frame), gt_labels=np.concatenate(gt_labels),
                  gt_boxes=np.concatenate(gt_boxes))
    passes = {}
    for spec in specs:
        parts = rows[spec.name]
        cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        passes[spec.name] = Passes(
            method=spec.name, n_members=spec.n_members, n_frames=len(seeds),
            member=cat["member"], frame=cat["frame"], query=cat["query"],
            layer_logits=cat["layer_logits"], layer_boxes=cat["layer_boxes"],
            seconds=seconds[spec.name], token_cell=token_cell, attn_cov=cat.get("attn_cov"))
    return truth, passes


def _models(sensor: str, spec: MethodSpec) -> list:
    """The detectors of a spec: one MC-dropout model, or one eval model per member."""
    from detectors.infer import enable_mc_dropout
    from detectors.registry import build_detector

    if spec.name == "mcd":
        return [enable_mc_dropout(build_detector(sensor, weights=spec.weights[0]))]
    models = [build_detector(sensor, weights=w) for w in spec.weights]
    if spec.name == "dse":
        from detectors.subensemble import same_trunk

        for w, m in zip(spec.weights[1:], models[1:], strict=True):
            if not same_trunk(models[0], m):
                raise ValueError(f"{w} is not a sub-ensemble head of {spec.weights[0]}: its "
                                 "trunk differs (retrain it with --base-weights)")
    return models


def _keep(outputs: dict, model: object, method: str, max_detections: int, frame: int,
          member: int) -> dict[str, np.ndarray]:
    """The rows one pass contributes (vanilla: top queries, all layers, attention C_K)."""
    from detectors.infer import postprocess
    from detectors.uncertainty import attention_spread

    if method != "vanilla":   # every query, final layer: merged by query index later
        logits = outputs["pred_logits"][-1, 0][:, None].numpy()
        boxes = outputs["pred_boxes"][-1, 0][:, None].numpy()
        query = np.arange(len(logits), dtype=np.int64)
        extra: dict[str, np.ndarray] = {}
    else:
        # One detection per query: the passes of every method are merged by query index.
        (det,) = postprocess(outputs, max_detections, decode="query")
        logits, boxes = det.layer_logits.numpy(), det.layer_boxes.numpy()
        query = det.query_index.numpy().astype(np.int64)
        centres = model.token_centres.double()  # type: ignore[attr-defined]
        attention = outputs["attention"][:, 0, det.query_index].double()   # [L, K, T]
        cov = [attention_spread(a, centres, top_k=ATTENTION_TOP_K).covariance.numpy()
               for a in attention]
        extra = {"attn_cov": np.stack(cov, axis=1)}                        # [K, L, 2, 2]
    n = len(query)
    return {"member": np.full(n, member, dtype=np.int64),
            "frame": np.full(n, frame, dtype=np.int64), "query": query,
            "layer_logits": logits.astype(np.float32),
            "layer_boxes": boxes.astype(np.float32), **extra}


def _save(path: Path, key: str, p: Passes) -> None:
    arrays = {"key": np.array(key), "method": np.array(p.method),
              "n_members": np.array(p.n_members), "n_frames": np.array(p.n_frames),
              "member": p.member, "frame": p.frame, "query": p.query,
              "layer_logits": p.layer_logits, "layer_boxes": p.layer_boxes,
              "seconds": p.seconds, "token_cell": np.array(p.token_cell)}
    if p.attn_cov is not None:
        arrays["attn_cov"] = p.attn_cov
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)


def _load(path: Path, key: str, n_members: int) -> Passes | None:
    """The cached passes if the file exists with `key` and >= `n_members` members."""
    if not path.exists():
        return None
    with np.load(path) as z:
        if str(z["key"]) != key or int(z["n_members"]) < n_members:
            return None
        p = Passes(method=str(z["method"]), n_members=int(z["n_members"]),
                   n_frames=int(z["n_frames"]), member=z["member"], frame=z["frame"],
                   query=z["query"], layer_logits=z["layer_logits"],
                   layer_boxes=z["layer_boxes"], seconds=z["seconds"],
                   token_cell=float(z["token_cell"]),
                   attn_cov=z["attn_cov"] if "attn_cov" in z else None, from_cache=True)
    return p if p.n_members == n_members else p.first_members(n_members)


def _save_truth(path: Path, key: str, t: Truth) -> None:
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, key=np.array(key), seeds=t.seeds, frame_ids=t.frame_ids,
             gt_frame=t.gt_frame, gt_labels=t.gt_labels, gt_boxes=t.gt_boxes)
    tmp.replace(path)


def _load_truth(path: Path, key: str) -> Truth | None:
    if not path.exists():
        return None
    with np.load(path) as z:
        if str(z["key"]) != key:
            return None
        return Truth(seeds=z["seeds"], frame_ids=z["frame_ids"], gt_frame=z["gt_frame"],
                     gt_labels=z["gt_labels"], gt_boxes=z["gt_boxes"])
