"""`detcal export`: write a profile's calibration as an ONNX or TorchScript graph.

PROFILE is a profile JSON file (read as `detcal calibrate --profile` reads it) or a stored
profile, `name`, `name@version` or `name@alias`, resolved in the store of `--data-dir` (or
`DETCAL_DATA_DIR`, `DETCAL_DATABASE_URL`) as the service resolves a request's `profile`.
torch and onnx are imported by the handler only (the `export` extra).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from app.cli.main import CliError
from app.cli.offline import load_profile
from calibrators.core.defaults import DEFAULT_LEVELS
from calibrators.core.vocab import COV_SOURCES

EXPORT_DESCRIPTION = """\
Write the profile's score calibration, covariance scaling and regions as a graph that takes
the detector's tensors (logits or per-layer logits, boxes or per-layer boxes, the raw
covariance for cov_source 'given', the box hypotheses and group scores for 'hypotheses', ego
position) and returns calibrated scores, covariances and ellipses; see docs/export.md."""

def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `export` subcommand."""
    ex = subparsers.add_parser(
        "export", help="write a profile's calibration as an ONNX or TorchScript graph",
        description=EXPORT_DESCRIPTION)
    ex.add_argument("profile", metavar="PROFILE",
                    help="profile JSON file, or a stored profile: name, name@version or "
                         "name@alias")
    # --format and --input-dtype are checked by detectors.export (its EXPORT_FORMATS and
    # INPUT_DTYPES), which needs torch: listing them here would import it for --help.
    ex.add_argument("--format", default="onnx",
                    help="graph format: onnx or torchscript (default: %(default)s)")
    ex.add_argument("--out", required=True, help="file to write")
    ex.add_argument("--levels", nargs="+", type=float, metavar="Q",
                    default=list(DEFAULT_LEVELS),
                    help="coverage levels of the ellipses, each in (0, 1), at most 20 "
                         "(default: %(default)s)")
    ex.add_argument("--cov-source", choices=COV_SOURCES, default=None,
                    help="covariance source the graph serves (default: the profile's own)")
    ex.add_argument("--layer-logits", action=argparse.BooleanOptionalAction, default=None,
                    help="take every decoder layer's logits [N, L, C'] (default: only when "
                         "the profile modulates, which needs them)")
    ex.add_argument("--input-dtype", default="float64",
                    help="dtype of the ONNX graph's float inputs, float64 or float32 (default: "
                         "%(default)s; the graph computes in float64 either way)")
    ex.add_argument("--labels", action="store_true",
                    help="take a labels [N] int64 input after the logits: the class each "
                         "detection asserts (top-K (query, class) decoding; default: the "
                         "arg-max of the logits)")
    ex.add_argument("--data-dir", help="service data directory holding the profile store "
                                       "(default: DETCAL_DATA_DIR or ./data)")
    ex.set_defaults(func=run_export)


def run_export(args: argparse.Namespace) -> int:
    """`detcal export`: resolve the profile, write the graph, say what it takes and gives."""
    try:
        from detectors.export import export_profile
    except ImportError as exc:
        raise CliError(f"exporting needs the export extra (pip install 'detcal[export]'): "
                       f"{exc}") from None

    profile, name = _profile(args.profile, args.data_dir)
    meta = export_profile(profile, args.out, args.format, cov_source=args.cov_source,
                          levels=args.levels, layer_logits=args.layer_logits,
                          input_dtype=args.input_dtype, labels=args.labels)
    print(f"wrote {args.out}: {args.format} graph of {name} (cov_source {meta['cov_source']}, "
          f"levels {meta['levels']}); inputs {', '.join(meta['inputs'])}; outputs "
          f"{', '.join(meta['outputs'])}", file=sys.stderr)
    return 0


def _profile(ref: str, data_dir: str | None) -> tuple[Any, str]:
    """The profile named by PROFILE and how to call it: a JSON file, else a stored profile."""
    if Path(ref).is_file() or ref.lower().endswith(".json"):
        return load_profile(ref), ref
    from app.calibrate.cache import ProfileCache
    from app.http.errors import RequestError
    from app.settings import Settings
    from app.store import NotFoundError, Store

    settings = Settings() if data_dir is None else Settings(data_dir=Path(data_dir))
    database = settings.data_dir / "detcal.db"
    if settings.database_url is None and not database.is_file():
        raise CliError(f"{ref}: no such profile file, and no profile store at {database} "
                       f"(--data-dir)")
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    try:
        loaded = ProfileCache(store).resolve(ref, settings.default_profile, loc=("PROFILE",))
    except RequestError as exc:
        raise CliError(f"PROFILE: {exc.msg}") from None
    except NotFoundError as exc:
        raise CliError(f"{exc}") from None
    except ValueError as exc:
        raise CliError(f"{ref}: the stored profile is not valid: {exc}") from None
    finally:
        store.close()
    return loaded.profile, loaded.record.ref
