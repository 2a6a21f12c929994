"""Fitting a profile: `fit_profile(dump, FitOptions())` in memory, `fit_profile_stream` over a
Parquet dataset (optionally on Dask).

- `_options`: `FitOptions`, every fit option with its check and help text.
- `_pipeline`: the in-memory fit: split, score stage, covariance stage, region stage, report.
- `_score_stage`, `_region_stage`: the stages (candidates fit, chosen on the calibration part).
- `_stream`, `_chunks`, `_distributed`: the streamed fit, its per-chunk passes, Dask.
"""

from calibrators.core.errors import OptionError
from calibrators.fit._chunks import (
    Chunk,
    FirstPass,
    first_pass,
    frames_of,
    sigmoid_range,
    softmax_rows,
    softmax_sums,
)
from calibrators.fit._distributed import Mapper, dask_client, parse_dask_spec
from calibrators.fit._options import FitOptions, OptionSpec
from calibrators.fit._pipeline import (
    base_profile,
    check_fit_input,
    fit_profile,
    selection_of,
    versioned,
)
from calibrators.fit._region_stage import (
    CovarianceFit,
    RegionFit,
    covariance_fit,
    fit_covariance_stage,
    fit_region_stage,
)
from calibrators.fit._score_stage import ScoreFit, fit_score_stage
from calibrators.fit._stream import check_stream_options, fit_profile_stream

__all__ = ["Chunk", "CovarianceFit", "FirstPass", "FitOptions", "Mapper", "OptionError",
           "OptionSpec", "RegionFit", "ScoreFit", "base_profile", "check_fit_input",
           "check_stream_options", "covariance_fit", "dask_client", "first_pass",
           "fit_covariance_stage", "fit_profile", "fit_profile_stream", "fit_region_stage",
           "fit_score_stage", "frames_of", "parse_dask_spec", "selection_of", "sigmoid_range",
           "softmax_rows", "softmax_sums", "versioned"]
