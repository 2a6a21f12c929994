"""One set of fit options: `detcal fit`, POST /v1/fit and the job runner all take FitOptions
(and, for a COCO pair, FitOptions2D: `app.fitting.options` joins the two)."""

from __future__ import annotations

import argparse

from app.cli.offline import add_fit_options, fit_options_of
from app.fitting.options import fit_option_specs
from app.main import create_app
from calibrators import FitOptions
from calibrators.boxes2d import FitOptions2D
from tests.app.conftest import ADMIN


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_fit_options(parser)
    return parser


def test_cli_flags_are_the_fit_options_with_their_defaults():
    parser = _parser()
    flags = {a.dest: a for a in parser._actions if a.dest != "help"}
    specs = {s.name: s for s in fit_option_specs()}
    assert set(flags) == set(specs) == {s.name for s in FitOptions.describe()} | {
        s.name for s in FitOptions2D.describe()}
    for name, spec in specs.items():
        assert flags[name].default == spec.default, name
        assert flags[name].option_strings[0] == "--" + name.replace("_", "-")
    assert fit_options_of(parser.parse_args([])) == FitOptions()
    args = parser.parse_args(["--modulation", "--dims", "x,y,yaw", "--min-score", "0.2"])
    assert fit_options_of(args) == FitOptions(modulation=True, dims=("x", "y", "yaw"),
                                              min_score=0.2)
    args = parser.parse_args(["--score-method", "position", "--iou-threshold", "0.7"])
    assert fit_options_of(args, coco=True) == FitOptions2D(score_method="position",
                                                           iou_threshold=0.7)


def test_fit_form_fields_are_the_fit_options_with_their_defaults(settings):
    schema = create_app(settings).openapi()["components"]["schemas"]["FitForm"]["properties"]
    specs = {s.name: s for s in fit_option_specs()}
    assert set(schema) == set(specs)
    for name, spec in specs.items():
        assert schema[name].get("default") == spec.default, name
    assert schema["cov_source"]["enum"] == list(specs["cov_source"].choices)


def test_bad_option_is_a_422_naming_the_field(empty_client, npz_bytes):
    for data, field in (({"threshold": "0"}, "threshold"), ({"dims": "x,q"}, "dims"),
                        ({"holdout": "1"}, "holdout"), ({"seed": "-3"}, "seed"),
                        ({"threshold": "nan"}, "threshold")):
        r = empty_client.post("/v1/fit", headers=ADMIN, data=data,
                              files={"dump": ("val.npz", npz_bytes)})
        assert r.status_code == 422, (data, r.text)
        assert r.json()["detail"][0]["loc"] == ["body", field], r.json()


def test_api_docs_list_every_fit_option_with_its_default():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[3] / "docs" / "api.md").read_text()
    section = text[text.index("## POST /v1/fit"):text.index("## GET /v1/jobs")]
    for spec in fit_option_specs():
        row = next((line for line in section.splitlines()
                    if line.startswith(f"| `{spec.name}` |")), None)
        assert row is not None, spec.name
        defaults = ("all", "none") if spec.default is None else (str(spec.default).lower(),)
        assert any(d in row.lower() for d in defaults), (spec.name, row)
