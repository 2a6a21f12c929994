"""Regions: the served uncertainty ellipses of a detection's position and their coverage levels.

- ellipses (`_ellipse`): the confidence ellipse of the `x, y` block of `Σ'`, semi-axes
  `r · sqrt(λ)` and the major-axis angle from +x; `chi2_2_quantile`, the Gaussian radius².
- levels (`_levels`): the coverage levels a request may name (`MAX_LEVELS`, `check_levels`),
  the Gaussian radius of a level, and the distance bins of a region group.
- conformal (`_conformal`): split-conformal radii per class × distance-bin group,
  `ConformalRegions`, over the partition of cells into groups (`_partition`); a group's
  order statistics, cell floors and training-conditional ranks (`_groups`), and what each
  served radius guarantees (`GUARANTEES`).
"""

from calibrators.regions._conformal import ConformalRegions
from calibrators.regions._ellipse import (
    Ellipse,
    chi2_2_quantile,
    ellipse,
    radius_ellipse,
    radius_ellipses,
    xy_mahalanobis,
)
from calibrators.regions._groups import GUARANTEES, ConformalGroup, stored_ranks
from calibrators.regions._levels import (
    DEFAULT_DISTANCE_EDGES,
    MAX_LEVELS,
    check_distance_edges,
    check_levels,
    distance_bins,
    gaussian_radius,
)

__all__ = ["DEFAULT_DISTANCE_EDGES", "GUARANTEES", "MAX_LEVELS", "ConformalGroup",
           "ConformalRegions", "Ellipse", "chi2_2_quantile", "check_distance_edges",
           "check_levels", "distance_bins", "ellipse", "gaussian_radius", "radius_ellipse",
           "radius_ellipses", "stored_ranks", "xy_mahalanobis"]
