"""`detcal convert` and `detcal fit OUT_DIR [--dask ...]` end to end (real subprocesses)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from calibrators.data import synthetic_dump
from calibrators.io import load_parquet, save_dump
from calibrators.profile import CalibrationProfile
from tests.app.cli.detcal_process import detcal as run_detcal


def detcal(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return run_detcal(*args, cwd=cwd, timeout=180)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli_stream")
    save_dump(path / "val.npz", synthetic_dump(n_frames=40, seed=17))
    save_dump(path / "soft.npz", synthetic_dump(n_frames=12, seed=18, score_mode="softmax"))
    for npz, out in (("val.npz", "ds"), ("soft.npz", "soft")):
        result = detcal("convert", npz, out, "--rows-per-part", "200", cwd=path)
        assert result.returncode == 0, result.stderr
    return path


def profile(path: Path) -> CalibrationProfile:
    return CalibrationProfile.from_json(path.read_text())


def test_convert_round_trips_the_dump(workdir):
    from calibrators.io import load_dump

    dump, back = load_dump(workdir / "val.npz"), load_parquet(workdir / "ds")
    assert (back.det_logits == dump.det_logits).all() and back.n_frames == dump.n_frames
    assert (back.gt_boxes == dump.gt_boxes).all()
    assert len(list((workdir / "ds" / "detections").glob("part-*.parquet"))) > 2


def test_streamed_and_dask_fits_equal_the_npz_fit(workdir):
    """With the default options: score candidates, covariance and regions chosen on the
    calibration part, streamed here and on two Dask workers, serve what the NPZ fit serves."""
    from calibrators.io import load_dump
    from calibrators.profile import apply_profile

    flags = ["--holdout", "0.2", "--quiet"]
    for args in (["val.npz", "--out", "npz.json"], ["ds", "--out", "stream.json"],
                 ["ds", "--out", "dask.json", "--dask", "local:2"]):
        result = detcal("fit", *args, *flags, cwd=workdir)
        assert result.returncode == 0, result.stderr
        assert "ECE" in result.stdout
    npz, stream, dask = (profile(workdir / f"{n}.json") for n in ("npz", "stream", "dask"))
    assert stream.provenance["dump_sha256"] == npz.provenance["dump_sha256"]
    dump = load_dump(workdir / "val.npz")
    for other in (stream, dask):
        assert other.temperature == pytest.approx(npz.temperature, rel=1e-6)
        assert other.score_method == npz.score_method
        assert abs(apply_profile(dump, other).scores - apply_profile(dump, npz).scores
                   ).max() < 1e-6
        for c, k in npz.depth_k.items():
            assert other.depth_k[c] == pytest.approx(k, rel=1e-4)


@pytest.mark.parametrize("args, message", [
    (["fit", "soft"], "cannot reproduce score_method='auto' on softmax"),
    (["fit", "ds", "--calibration", "0", "--dask", "somewhere"], "dask must be 'local'"),
    (["fit", "val.npz", "--dask", "local:2"], "--dask needs a Parquet dataset folder"),
    (["fit", "nothing_here", "--calibration", "0"], "nothing_here: no such file"),
    (["convert", "val.npz", "ds"], "already holds a Parquet dataset"),
])
def test_bad_input_exits_2_with_one_line(workdir, args, message):
    result = detcal(*args, cwd=workdir)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr


def test_a_folder_that_is_not_a_dataset_is_named(workdir):
    (workdir / "plain").mkdir(exist_ok=True)
    result = detcal("fit", "plain", "--calibration", "0", cwd=workdir)
    assert result.returncode == 2 and "has no detcal.json" in result.stderr
