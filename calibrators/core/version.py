"""The installed detcal version (recorded in every profile's provenance and served by the API)."""

from __future__ import annotations


def detcal_version() -> str:
    """The installed detcal distribution's version, `"unknown"` when run from a bare tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("detcal")
    except PackageNotFoundError:
        return "unknown"
