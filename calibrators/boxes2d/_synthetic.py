"""A synthetic 2-D validation set in COCO form, for tests, examples and the docs' tours: an
instances document and the results of a detector that is overconfident in a known way.

Each image (640 x 480) holds a few objects of `n_categories` categories. The detector finds
each object with probability 0.9. Its query's box at each of `n_layers` decoder layers is the
true box jittered by `m` (a uniform quality in [0, 1]) times a quarter of the box size, twice
that in the right half of the image; the final layer's box is the detection. Its score is
`1 − 0.5·m`: it ignores the right half, and it is too high overall. Each image also gets up to
two false positives (boxes with no object, scores uniform in [0.3, 0.9]). The images are
drawn independently, so any split of them is exchangeable.

With `logits=True` every record carries sigmoid logits `[C]` (the label's column is the
score's logit, the others are low), read with `score_mode="sigmoid"` in the instances'
category order.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["SYNTHETIC_CATEGORIES", "synthetic_coco"]

#: The category names of `synthetic_coco`, ids 1, 2, ... in this order.
SYNTHETIC_CATEGORIES: tuple[str, ...] = ("car", "person", "bicycle", "truck")
_WIDTH, _HEIGHT = 640, 480


def synthetic_coco(n_images: int = 400, seed: int = 0, *, n_categories: int = 2,
                   n_layers: int = 4, logits: bool = False
                   ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """`(results, instances)`: a COCO results list (`image_id`, `category_id`, `bbox`,
    `score`, `layer_boxes [L][4]` with `n_layers` >= 2, `logits [C]` with `logits`) and its
    instances document (`images`, `annotations`, `categories`), as the module docstring draws
    them; the same arguments give the same documents."""
    if not 1 <= n_categories <= len(SYNTHETIC_CATEGORIES):
        raise ValueError(f"n_categories must be in 1..{len(SYNTHETIC_CATEGORIES)}")
    if n_layers < 2 or n_images < 1:
        raise ValueError("n_layers must be >= 2 and n_images >= 1")
    rng = np.random.default_rng(seed)
    images, annotations, results = [], [], []
    for image in range(1, n_images + 1):
        images.append({"id": image, "width": _WIDTH, "height": _HEIGHT})
        for _ in range(int(rng.integers(2, 5))):
            w, h = rng.uniform(20, 200, 2)
            x, y = rng.uniform(0, _WIDTH - w), rng.uniform(0, _HEIGHT - h)
            cat = int(rng.integers(1, n_categories + 1))
            annotations.append({"id": len(annotations) + 1, "image_id": image,
                                "category_id": cat, "bbox": [x, y, w, h], "area": w * h,
                                "iscrowd": 0})
            if rng.random() >= 0.9:
                continue
            m = rng.random()
            spread = m * (0.25 if x + w / 2 < _WIDTH / 2 else 0.5) * np.array([w, h, w, h])
            layers = np.abs([x, y, w, h] + rng.normal(0, 1, (n_layers, 4)) * spread)
            results.append(_record(image, cat, layers, 1.0 - 0.5 * m))
        for _ in range(int(rng.integers(0, 3))):
            w, h = rng.uniform(20, 120, 2)
            box = [rng.uniform(0, _WIDTH - w), rng.uniform(0, _HEIGHT - h), w, h]
            layers = np.abs(box + rng.normal(0, 0.1, (n_layers, 4)) * [w, h, w, h])
            results.append(_record(image, int(rng.integers(1, n_categories + 1)), layers,
                                   float(rng.uniform(0.3, 0.9))))
    if logits:
        for r in results:
            z = np.full(n_categories, -6.0)
            z[r["category_id"] - 1] = np.log(r["score"]) - np.log1p(-r["score"])
            r["logits"] = z.tolist()
    categories = [{"id": i + 1, "name": SYNTHETIC_CATEGORIES[i]} for i in range(n_categories)]
    return results, {"images": images, "annotations": annotations, "categories": categories}


def _record(image: int, category: int, layers: np.ndarray, score: float) -> dict[str, Any]:
    return {"image_id": image, "category_id": category, "bbox": layers[-1].tolist(),
            "score": float(np.clip(score, 1e-6, 1.0 - 1e-6)), "layer_boxes": layers.tolist()}
