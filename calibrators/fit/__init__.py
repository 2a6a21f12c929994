"""Fitting a profile: `fit_profile(dump, FitOptions())` in memory, `fit_profile_stream` over a
Parquet dataset (optionally on Dask).

- `_options`: `FitOptions`, every fit option with its check and help text.
- `_pipeline`: the in-memory fit: split, score stage, covariance stage, region stage, report.
- `_score_stage`, `_region_stage`: the stages (candidates fit, chosen on the calibration part).
- `_stream`, `_chunks`, `_distributed`: the streamed fit, its per-chunk passes, Dask.
"""

from calibrators.core.errors import OptionError
from calibrators.fit._distributed import Mapper, dask_client, parse_dask_spec
from calibrators.fit._options import (
    FitOptions,
    OptionSpec,
    describe_options,
    option_integer,
    option_number,
    options_from_dict,
)
from calibrators.fit._pipeline import check_fit_input, fit_profile
from calibrators.fit._region_stage import CovarianceFit, RegionFit, conformal_region_fit
from calibrators.fit._score_stage import ScoreFit
from calibrators.fit._stream import check_stream_options, fit_profile_stream

__all__ = ["CovarianceFit", "FitOptions", "Mapper", "OptionError", "OptionSpec", "RegionFit",
           "ScoreFit", "check_fit_input", "conformal_region_fit",
           "check_stream_options", "dask_client", "describe_options", "fit_profile",
           "fit_profile_stream", "option_integer", "option_number", "options_from_dict",
           "parse_dask_spec"]
