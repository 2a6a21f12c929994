"""The held-out criteria of `bench.bench_cells`: a cell is judged on one side (below its level
by more than the allowance), a class on both sides, as the per-cell issue states them."""

from __future__ import annotations

import numpy as np

from bench.bench_cells import LEVELS, Served, shortfalls

CLASSES = ("car", "bus")


def _served(covered: dict[tuple[int, int], float], n: int = 1000) -> Served:
    """`n` test true positives in each (class, distance bin) of `covered`, a share of them
    inside radius 1 at every level (maha 0.5) and the rest outside (maha 2)."""
    labels, distance, maha = [], [], []
    for (cls, where), share in covered.items():
        inside = round(share * n)
        labels += [cls] * n
        distance += [(7.5, 22.5, 45.0)[where]] * n
        maha += [0.5] * inside + [2.0] * (n - inside)
    m = len(labels)
    none = np.zeros(0)
    return Served(np.asarray(maha), np.asarray(labels), np.asarray(distance),
                  np.ones((m, len(LEVELS))), none, none.astype(bool), none.astype(int))


def test_a_class_over_its_level_is_a_shortfall_and_a_cell_over_it_is_not():
    exact = {(0, 0): 0.9, (0, 1): 0.9, (0, 2): 0.9}
    over = {(1, 0): 1.0, (1, 1): 1.0, (1, 2): 1.0}
    found = shortfalls(_served({**exact, **over}), CLASSES, 200, 500)
    at_90 = [line for line in found if "@ 0.9:" in line]
    assert at_90 == ["bus all @ 0.9: 1.000 (3000) over"], found


def test_a_cell_under_its_level_is_a_shortfall():
    found = shortfalls(_served({(0, 0): 0.92, (0, 1): 0.85, (0, 2): 0.92}), CLASSES, 200, 500)
    assert "car 15-30 m @ 0.9: 0.850 (1000)" in found
    assert not any(line.startswith("car all @ 0.9:") for line in found)   # 0.897: within
