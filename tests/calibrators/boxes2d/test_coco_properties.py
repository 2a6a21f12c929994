"""evaluate_coco against pycocotools on random COCO-format data (Hypothesis), and what the
evaluation must not depend on.

The boxes sit on a 4 px grid with sizes from a short list, and some ground-truth boxes are
shifted copies of others, so equal IoUs, IoUs exactly at a threshold, empty boxes, and areas
exactly at a range edge all come up; scores come from a
short list too (ties) unless a test needs them distinct. Some detections are shifted copies of
a ground-truth box (true positives and duplicates), some carry another category.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.calibrators.boxes2d.reference import (
    assert_same,
    coco_dataset,
    run_ours,
    run_pycocotools,
)

SETTINGS = settings(max_examples=120, deadline=None)
GRID = st.integers(0, 8).map(lambda v: 8.0 * v)
SIZE = st.sampled_from([0.0, 4.0, 8.0, 16.0, 24.0, 32.0, 40.0, 64.0, 96.0, 100.0, 120.0])
SHIFT = st.sampled_from([-8.0, -4.0, 0.0, 0.0, 0.0, 4.0, 8.0])
AREA_EDGES = st.sampled_from([0.0, 500.0, 1024.0, 5000.0, 9216.0, 1e10, 2e10])
TIED_SCORE = st.sampled_from([0.1, 0.5, 0.5, 0.9, 1.0])


@st.composite
def coco_data(draw, distinct_scores: bool = False, ignore: bool = False):
    """(dataset, results): 1-4 images, 1-3 categories, 0-6 boxes and 0-12 detections per
    image, listed in random order, at least one (pycocotools' loadRes needs one)."""
    n_images, n_cats = draw(st.integers(1, 4)), draw(st.integers(1, 3))
    category = st.integers(1, n_cats)
    annotations, results = [], []
    for image in range(1, n_images + 1):
        boxes = []
        for _ in range(draw(st.integers(0, 6))):
            if boxes and draw(st.integers(0, 2)) == 0:  # a neighbour: equal IoUs around
                (x, y, w, h), cat = draw(st.sampled_from(boxes))
                box = [x + draw(SHIFT), y + draw(SHIFT), w, h]
            else:
                box, cat = [draw(GRID), draw(GRID), draw(SIZE), draw(SIZE)], draw(category)
            area = draw(st.one_of(st.just(box[2] * box[3]), AREA_EDGES,
                                  st.floats(0, 20000, allow_nan=False)))
            ann = {"image_id": image, "category_id": cat, "bbox": box, "area": area,
                   "iscrowd": int(draw(st.integers(0, 7)) == 0)}
            if ignore:
                ann["keep_ignore"] = int(draw(st.integers(0, 4)) == 0)
            annotations.append(ann)
            boxes.append((box, cat))
        for _ in range(draw(st.integers(0, 12))):
            if boxes and draw(st.booleans()):
                (x, y, w, h), cat = draw(st.sampled_from(boxes))
                box = [x + draw(SHIFT), y + draw(SHIFT), max(w + draw(SHIFT), 0.0),
                       max(h + draw(SHIFT), 0.0)]
                cat = draw(category) if draw(st.integers(0, 5)) == 0 else cat
            else:
                box, cat = [draw(GRID), draw(GRID), draw(SIZE), draw(SIZE)], draw(category)
            score = 0.0 if distinct_scores else draw(st.one_of(TIED_SCORE, st.floats(0, 1)))
            results.append({"image_id": image, "category_id": cat, "bbox": box,
                            "score": score})
    if not results:
        results.append({"image_id": 1, "category_id": 1, "bbox": [0.0, 0.0, 8.0, 8.0],
                        "score": 0.5})
    results = draw(st.permutations(results))  # rows in no particular image order
    if distinct_scores:
        for r, rank in zip(results, draw(st.permutations(range(len(results)))), strict=True):
            r["score"] = (rank + 1) / (len(results) + 1)
    dataset = coco_dataset(annotations, range(1, n_images + 1), range(1, n_cats + 1))
    return dataset, results


@SETTINGS
@given(coco_data())
def test_equals_pycocotools(data):
    dataset, results = data
    assert_same(run_ours(dataset, results), run_pycocotools(dataset, results))


@SETTINGS
@given(coco_data(ignore=True))
def test_the_ignore_flag_equals_pycocotools_keeping_it(data):
    dataset, results = data
    assert_same(run_ours(dataset, results), run_pycocotools(dataset, results, keep_ignore=True))


@settings(max_examples=60, deadline=None)
@given(coco_data(distinct_scores=True), st.randoms(use_true_random=False))
def test_permuting_detections_changes_nothing_without_ties(data, random):
    dataset, results = data
    shuffled = list(results)
    random.shuffle(shuffled)
    before, after = run_ours(dataset, results), run_ours(dataset, shuffled)
    np.testing.assert_array_equal(after.precision, before.precision)
    np.testing.assert_array_equal(after.recall, before.recall)
    np.testing.assert_array_equal(after.stats, before.stats)


@settings(max_examples=60, deadline=None)
@given(coco_data(distinct_scores=True), st.randoms(use_true_random=False))
def test_renumbering_images_changes_nothing_without_ties(data, random):
    dataset, results = data
    ids = [i["id"] for i in dataset["images"]]
    new = dict(zip(ids, random.sample([10 * i for i in ids], len(ids)), strict=True))
    renumbered = coco_dataset([{**a, "image_id": new[a["image_id"]]}
                               for a in dataset["annotations"]],
                              sorted(new.values()), [c["id"] for c in dataset["categories"]])
    moved = [{**r, "image_id": new[r["image_id"]]} for r in results]
    before, after = run_ours(dataset, results), run_ours(renumbered, moved)
    np.testing.assert_array_equal(after.precision, before.precision)
    np.testing.assert_array_equal(after.stats, before.stats)
