"""The `detcal` CLI end to end: real subprocesses of the installed entry point."""

from __future__ import annotations

import json

import pytest

from app.cli.main import main
from calibrators.data import synthetic_dump
from calibrators.io import save_dump
from calibrators.profile import CalibrationProfile
from tests.app.cli.detcal_process import detcal


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli")
    save_dump(path / "val.npz", synthetic_dump(n_frames=40, seed=7))
    (path / "broken.npz").write_bytes(b"this is not an npz file")
    return path


@pytest.fixture(scope="module")
def fitted(workdir):
    result = detcal("fit", "val.npz", "--out", "profile.json", "--holdout", "0.25",
                    "--min-samples", "20", cwd=workdir)
    assert result.returncode == 0, result.stderr
    return result


def test_help_lists_the_calibration_commands(workdir):
    result = detcal("--help", cwd=workdir)
    assert result.returncode == 0
    for command in ("fit", "evaluate", "calibrate"):
        assert command in result.stdout


def test_fit_prints_the_table_and_writes_a_loadable_profile(fitted, workdir):
    assert "ECE" in fitted.stdout and "before" in fitted.stdout and "after" in fitted.stdout
    assert "held-out part" in fitted.stdout
    assert "detcal fit: match" in fitted.stderr          # progress on stderr
    profile = CalibrationProfile.from_json((workdir / "profile.json").read_text())
    assert profile.cov_source == "given" and profile.cov_dims == ("x", "y")
    assert 1.5 < profile.temperature < 2.6
    assert profile.report["holdout"] is not None
    assert len(profile.provenance["dump_sha256"]) == 64


def test_fit_prints_each_stage_chosen_method_and_its_held_out_score(fitted, workdir):
    profile = CalibrationProfile.from_json((workdir / "profile.json").read_text())
    lines = {line.split()[0]: line for line in fitted.stdout.splitlines()
             if line.startswith("  ") and line.split()[0] in ("score", "covariance", "regions")}
    assert f" {profile.score_method} " in lines["score"] and "ECE" in lines["score"]
    assert f" {profile.cov_method} " in lines["covariance"] and "NLL" in lines["covariance"]
    assert f" {profile.region_method} " in lines["regions"]
    assert "held-out coverage 0.5:" in lines["regions"]           # fit with --holdout 0.25
    help_text = detcal("fit", "--help", cwd=workdir).stdout
    assert "the per-class depth k" not in help_text and "score calibration" in help_text


def test_evaluate_json_with_a_profile(fitted, workdir):
    result = detcal("evaluate", "val.npz", "--profile", "profile.json", "--json", cwd=workdir)
    assert result.returncode == 0, result.stderr
    doc = json.loads(result.stdout)
    assert set(doc) == {"evaluation", "evaluation_calibrated", "calibration"}
    assert 0.0 <= doc["evaluation"]["mean_ap"] <= 1.0
    ece = doc["calibration"]["classification"]["ece"]
    assert ece["after"] < ece["before"]


def test_evaluate_text_without_a_profile(workdir):
    result = detcal("evaluate", "val.npz", cwd=workdir)
    assert result.returncode == 0, result.stderr
    assert "mAP" in result.stdout and "AP@2.0" in result.stdout and "car" in result.stdout


def test_calibrate_writes_nuscenes_results(fitted, workdir):
    result = detcal("calibrate", "val.npz", "--profile", "profile.json", "--out", "res.json",
                    cwd=workdir)
    assert result.returncode == 0, result.stderr
    doc = json.loads((workdir / "res.json").read_text())
    boxes = [box for frame in doc["results"].values() for box in frame]
    assert boxes and all(0.0 <= box["detection_score"] <= 1.0 for box in boxes)


def _one_error_line(stderr: str, message: str) -> None:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and message in lines[0], stderr


@pytest.mark.parametrize(("args", "message"), [
    (("fit", "broken.npz"), "broken.npz"),
    (("evaluate", "missing.npz"), "no such file"),
])
def test_bad_file_exits_2_with_one_line(args, message, workdir):
    result = detcal(*args, cwd=workdir)
    assert result.returncode == 2
    _one_error_line(result.stderr, message)


@pytest.mark.parametrize(("args", "message"), [
    (("fit", "val.npz", "--holdout", "1.5"), "holdout"),
    (("fit", "val.npz", "--dims", "x,q"), "dims"),
    (("fit", "val.npz", "--cov-source", "given", "--dims", "x,y,z"), "cov_dims"),
    (("evaluate", "val.npz", "--profile", "val.npz"), "not a valid profile"),
    (("calibrate", "val.npz", "--profile", "missing.json"), "no such file"),
    (("calibrate", "val.npz", "--profile", "profile.json", "--out", "no/such/dir/x.json"),
     "no/such/dir"),
])
def test_bad_input_exits_2_with_one_line(args, message, workdir, fitted, capsys, monkeypatch):
    monkeypatch.chdir(workdir)   # same handler code as the subprocesses, run in-process
    assert main(list(args)) == 2
    _one_error_line(capsys.readouterr().err, message)
