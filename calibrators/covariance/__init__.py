"""Covariance: where a detection's box covariance comes from, and how it is scaled.

- hypotheses (`_hypotheses`): the checks of H box hypotheses and their score-weighted spread.
- sources (`_sources`): the one dispatch from a covariance source name (`given`, `layers`,
  `hypotheses`, `none`) to the arrays it reads (`SOURCE_ARRAYS`) and the uncalibrated Σ it
  gives (`source_covariance`); `layer_spread`, the spread across decoder layers (over any
  parametrisation: `sample_spread`).
- depth scaling (`_depth`, with its NLL `_depth_nll` on the log-distance grid `_depth_grid`,
  searched by `_depth_search`, over the eigen-decomposition of `_spectral`):
  `Σ' = Σ + k_c·d·I`, `DepthScaler`; its terms per detection (`DepthTerms`), their sums per
  log-distance bin (`BinSums`, `depth_bins`, on the grid of `log_bin` / `log_bin_low`:
  `MANTISSA_BITS` bins per octave over `OCTAVES` octaves), the Brent search of k (`brent_k`)
  and the eigen-decomposition of Σ in the whitened residual's frame (`spectral`,
  `spectral_2x2`).
- shrinkage (`_shrinkage`): `Σ' = s_c·Σ + k_c·d·I`, `ShrinkageDepthScaler`.
"""

from calibrators.covariance._depth import DepthScaler, add_depth_term, fit_inputs
from calibrators.covariance._depth_grid import MANTISSA_BITS, OCTAVES, log_bin, log_bin_low
from calibrators.covariance._depth_nll import BinSums, DepthTerms, depth_bins
from calibrators.covariance._depth_search import brent_k
from calibrators.covariance._hypotheses import check_hypotheses, hypotheses_covariance
from calibrators.covariance._shrinkage import ShrinkageDepthScaler, near_zero_q
from calibrators.covariance._sources import (
    SOURCE_ARRAYS,
    dim_indices,
    layer_spread,
    raw_covariances,
    resolve_cov_source,
    sample_spread,
    source_arrays,
    source_covariance,
    source_inputs,
    takes_phrase,
)
from calibrators.covariance._spectral import spectral, spectral_2x2

__all__ = ["MANTISSA_BITS", "OCTAVES", "SOURCE_ARRAYS", "BinSums", "DepthScaler", "DepthTerms",
           "ShrinkageDepthScaler", "add_depth_term", "brent_k", "check_hypotheses", "depth_bins",
           "dim_indices", "fit_inputs", "hypotheses_covariance", "layer_spread", "log_bin",
           "log_bin_low", "near_zero_q", "raw_covariances", "resolve_cov_source", "sample_spread",
           "source_arrays", "source_covariance", "source_inputs", "spectral", "spectral_2x2",
           "takes_phrase"]
