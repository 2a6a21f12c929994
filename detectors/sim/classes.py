"""Object classes of the simulated world: sizes, frequencies and materials.

Sizes follow the nuScenes training-set statistics (mean ``w, l, h`` in metres, with a
log-normal per-instance spread). Materials decide what each sensor sees: lidar
reflectivity (intensity), radar cross section (dBsm) and number of radar scattering
centres, and a camera colour palette. Palettes and materials deliberately overlap between
look-alike classes (pedestrian in hi-vis vs traffic cone, bicycle vs motorcycle,
truck vs construction vehicle vs bus), and the static street furniture (bins, bollards,
hydrants) looks like small objects to every sensor without being ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CLASSES: tuple[str, ...] = (
    "car",
    "truck",
    "bus",
    "trailer",
    "construction_vehicle",
    "pedestrian",
    "motorcycle",
    "bicycle",
    "traffic_cone",
    "barrier",
)

Palette = tuple[tuple[float, tuple[float, float, float]], ...]


@dataclass(frozen=True)
class Material:
    """What the sensors see of one kind of thing.

    reflectivity: lidar reflectivity mean and std (intensity in [0, 1]).
    rcs: radar cross section mean and std in dBsm (whole object).
    n_scatter: radar scattering centres per object (per 4 m of length for walls).
    palette: ((weight, (r, g, b)), ...) camera colours in [0, 1]; an instance draws one
        entry by weight and adds N(0, 0.06) per channel.
    """

    reflectivity: tuple[float, float]
    rcs: tuple[float, float]
    n_scatter: int
    palette: Palette


@dataclass(frozen=True)
class ClassSpec:
    """One object class: mean size ``(w, l, h)``, log-normal relative spread, free-draw weight."""

    name: str
    size: tuple[float, float, float]
    size_spread: tuple[float, float, float]
    weight: float
    material: Material


_WHITE = (0.86, 0.86, 0.84)
_BLACK = (0.10, 0.10, 0.11)
_SILVER = (0.58, 0.58, 0.60)
_RED = (0.62, 0.10, 0.10)
_BLUE = (0.15, 0.22, 0.52)
_YELLOW = (0.86, 0.70, 0.12)
_ORANGE = (0.90, 0.42, 0.10)
_GREEN = (0.18, 0.42, 0.22)
_CONCRETE = (0.60, 0.60, 0.57)

CLASS_SPECS: dict[str, ClassSpec] = {
    spec.name: spec
    for spec in (
        ClassSpec("car", (1.95, 4.62, 1.73), (0.08, 0.10, 0.10), 0.52,
                  Material((0.35, 0.15), (10.0, 3.0), 6,
                           ((0.25, _WHITE), (0.22, _BLACK), (0.25, _SILVER), (0.12, _RED),
                            (0.12, _BLUE), (0.04, _YELLOW)))),
        ClassSpec("truck", (2.52, 6.94, 2.84), (0.12, 0.25, 0.20), 0.085,
                  Material((0.36, 0.15), (17.0, 3.0), 10,
                           ((0.45, _WHITE), (0.15, _SILVER), (0.12, _RED), (0.1, _BLUE),
                            (0.12, _YELLOW), (0.06, _ORANGE)))),
        ClassSpec("bus", (2.94, 11.19, 3.47), (0.05, 0.15, 0.08), 0.02,
                  Material((0.40, 0.12), (18.0, 2.5), 12,
                           ((0.30, _WHITE), (0.25, _RED), (0.15, _YELLOW), (0.15, _BLUE),
                            (0.15, _GREEN)))),
        ClassSpec("trailer", (2.92, 12.28, 3.87), (0.10, 0.28, 0.15), 0.025,
                  Material((0.36, 0.15), (17.0, 3.0), 10,
                           ((0.45, _WHITE), (0.25, _SILVER), (0.15, _RED), (0.15, _BLUE)))),
        ClassSpec("construction_vehicle", (2.82, 6.44, 3.19), (0.15, 0.25, 0.22), 0.012,
                  Material((0.42, 0.15), (15.0, 3.0), 8,
                           ((0.55, _YELLOW), (0.20, _ORANGE), (0.15, _WHITE), (0.10, _RED)))),
        ClassSpec("pedestrian", (0.68, 0.73, 1.77), (0.15, 0.18, 0.10), 0.17,
                  Material((0.20, 0.08), (-5.0, 3.0), 2,
                           ((0.35, (0.16, 0.16, 0.19)), (0.20, (0.22, 0.27, 0.42)),
                            (0.15, (0.70, 0.70, 0.68)), (0.10, _RED), (0.10, _ORANGE),
                            (0.10, (0.80, 0.85, 0.20))))),
        ClassSpec("motorcycle", (0.77, 2.11, 1.47), (0.15, 0.10, 0.12), 0.022,
                  Material((0.30, 0.12), (2.0, 3.0), 3,
                           ((0.40, _BLACK), (0.20, _RED), (0.10, _BLUE), (0.15, _WHITE),
                            (0.15, _SILVER)))),
        ClassSpec("bicycle", (0.61, 1.70, 1.29), (0.18, 0.10, 0.10), 0.022,
                  Material((0.26, 0.12), (-3.0, 3.0), 2,
                           ((0.30, _BLACK), (0.30, _SILVER), (0.15, _RED), (0.15, _BLUE),
                            (0.10, _WHITE)))),
        ClassSpec("traffic_cone", (0.41, 0.41, 1.07), (0.15, 0.15, 0.18), 0.03,
                  Material((0.50, 0.18), (-10.0, 3.0), 1,
                           ((0.80, _ORANGE), (0.10, _RED), (0.10, _YELLOW)))),
        ClassSpec("barrier", (2.53, 0.50, 0.98), (0.12, 0.20, 0.12), 0.015,
                  Material((0.42, 0.15), (0.0, 3.0), 2,
                           ((0.40, _CONCRETE), (0.30, (0.80, 0.45, 0.45)), (0.20, _ORANGE),
                            (0.10, _YELLOW)))),
    )
}

STATIC_KINDS: tuple[str, ...] = (
    "wall", "pole", "tree_trunk", "tree_crown", "bin", "bollard", "hydrant", "bench",
)

STATIC_MATERIALS: dict[str, Material] = {
    "wall": Material((0.30, 0.10), (5.0, 3.0), 1,
                     ((0.4, (0.70, 0.62, 0.50)), (0.3, (0.55, 0.55, 0.55)),
                      (0.3, (0.55, 0.30, 0.22)))),
    "pole": Material((0.35, 0.10), (8.0, 2.0), 1, ((1.0, (0.40, 0.40, 0.42)),)),
    "tree_trunk": Material((0.25, 0.08), (-3.0, 3.0), 1, ((1.0, (0.30, 0.22, 0.15)),)),
    "tree_crown": Material((0.20, 0.08), (-12.0, 3.0), 2, ((1.0, (0.20, 0.40, 0.18)),)),
    "bin": Material((0.22, 0.10), (0.0, 3.0), 1,
                    ((0.5, (0.15, 0.30, 0.18)), (0.3, _SILVER), (0.2, _ORANGE))),
    "bollard": Material((0.45, 0.15), (-6.0, 3.0), 1,
                        ((0.5, (0.25, 0.25, 0.27)), (0.3, _SILVER), (0.2, _RED))),
    "hydrant": Material((0.35, 0.12), (-4.0, 3.0), 1, ((0.7, _RED), (0.3, _YELLOW))),
    "bench": Material((0.25, 0.10), (0.0, 3.0), 1,
                      ((0.6, (0.40, 0.28, 0.18)), (0.4, (0.20, 0.35, 0.22)))),
}

# (w, l, h) means and relative spreads of static street furniture (walls are sized by layout).
STATIC_SIZES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "pole": ((0.25, 0.25, 6.5), (0.1, 0.1, 0.15)),
    "tree_trunk": ((0.40, 0.40, 3.0), (0.2, 0.2, 0.15)),
    "bin": ((0.60, 0.60, 1.05), (0.15, 0.15, 0.10)),
    "bollard": ((0.28, 0.28, 0.95), (0.15, 0.15, 0.12)),
    "hydrant": ((0.40, 0.40, 0.75), (0.12, 0.12, 0.10)),
    "bench": ((0.60, 1.80, 0.85), (0.10, 0.12, 0.08)),
}

GROUND_MATERIAL = Material((0.08, 0.03), (-20.0, 3.0), 0, ((1.0, (0.28, 0.28, 0.29)),))
MARKING_MATERIAL = Material((0.60, 0.10), (-20.0, 3.0), 0, ((1.0, (0.85, 0.85, 0.82)),))
SIDEWALK_MATERIAL = Material((0.15, 0.05), (-20.0, 3.0), 0, ((1.0, (0.55, 0.54, 0.52)),))


def class_index(name: str) -> int:
    """Index of `name` in CLASSES, or a ValueError naming the valid classes."""
    if name not in CLASS_SPECS:
        raise ValueError(f"class {name!r} is not one of {CLASSES}")
    return CLASSES.index(name)


def sample_size(
    rng: np.random.Generator,
    mean: tuple[float, float, float],
    spread: tuple[float, float, float],
) -> np.ndarray:
    """One ``(w, l, h)`` drawn log-normally around `mean`, clipped to +-2.5 sigma. -> [3]."""
    z = np.clip(rng.standard_normal(3), -2.5, 2.5)
    return np.asarray(mean) * np.exp(z * np.asarray(spread))


def sample_material(
    rng: np.random.Generator, material: Material
) -> tuple[float, float, np.ndarray]:
    """Per-instance (reflectivity, rcs_dbsm, rgb [3]) drawn from `material`."""
    refl = float(np.clip(rng.normal(*material.reflectivity), 0.02, 1.0))
    rcs = float(rng.normal(*material.rcs))
    weights = np.array([w for w, _ in material.palette])
    pick = rng.choice(len(weights), p=weights / weights.sum())
    rgb = np.clip(np.asarray(material.palette[pick][1]) + rng.normal(0.0, 0.06, 3), 0.0, 1.0)
    return refl, rcs, rgb
