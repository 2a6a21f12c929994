"""`detcal report`: calibration vs sampling baselines per sensor, thesis-style (issue 5).

- `runner`: cached forward passes (vanilla, MC dropout, ensembles) per sensor and split;
- `dumps`: validation dumps from the passes, sampling members merged per frame;
- `rows`: one function per table row, all measured by `rows.measure`;
- `attention`: seed 000's attention-spread statistics;
- `tables` / `markdown`: the markdown; `plots`: the figures (PNG + SVG);
- `sensor`: one sensor's whole report; `cli`: the `detcal report` subcommand.
"""
