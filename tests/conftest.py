"""Suite-wide test settings.

Hypothesis: under CI (`CI` set, as `.ci/run` is called) the property tests draw the same
examples on every run (`derandomize`) and keep no example database, so a submission's result
does not depend on the draw; a developer's runs explore new examples each time and replay
the failures they found (`.hypothesis/`)."""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI"):
    settings.load_profile("ci")
