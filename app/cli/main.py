"""The `detcal` command line: subcommands registered by the modules that own them.

Each module in `REGISTRARS` exposes `register(subparsers)`, which adds its subcommands and sets
`func=handler(args) -> int` on each. Modules are imported lazily and one by one: if one is
missing or fails to import (e.g. the service extras are not installed), the others still work
and `detcal --help` lists what is unavailable.

Handlers raise `CliError` (or ValueError / OSError for bad input); `main` prints a one-line
`detcal COMMAND: error: ...` message and exits 2, with no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pickle
import sys
import zipfile
from collections.abc import Sequence

REGISTRARS = ("app.cli.offline", "app.cli.convert", "app.cli.serve", "app.cli.export",
              "detectors.cli", "detectors.report.cli")
USAGE_ERRORS = (ValueError, OSError, zipfile.BadZipFile, pickle.UnpicklingError)


class CliError(Exception):
    """A user error: printed as one line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    """The `detcal` parser with every subcommand whose module imports."""
    from calibrators.core.version import detcal_version

    parser = argparse.ArgumentParser(
        prog="detcal",
        description="Post-hoc calibration of DETR-family 3D and 2-D detectors: fit profiles "
                    "on validation dumps or COCO files, evaluate, calibrate detections, serve "
                    "the API.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {detcal_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    missing = []
    for name in REGISTRARS:
        try:
            module = importlib.import_module(name)
            module.register(sub)
        except Exception as exc:  # one broken extra must not break the other commands
            missing.append(f"{name} ({type(exc).__name__}: {exc})")
    if missing:
        parser.epilog = "unavailable command modules: " + "; ".join(missing)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run `detcal` with `argv` (default `sys.argv[1:]`); returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(func(args) or 0)
    except BrokenPipeError:   # e.g. `detcal evaluate ... | head`: stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except (CliError, *USAGE_ERRORS) as exc:
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"detcal {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"detcal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
