"""`python -m detectors.boxer2d train | evaluate | dump`: see `detectors.boxer2d.cli`."""

from detectors.boxer2d.cli import main

raise SystemExit(main())
