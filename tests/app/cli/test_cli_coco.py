"""`detcal fit --from coco` and `detcal calibrate` with a 2-D profile, end to end through the
installed entry point; README.md's 2-D tour runs as written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from calibrators.boxes2d import Profile2D, read_coco_results, synthetic_coco
from tests.app.cli.detcal_process import detcal
from tests.docs.test_examples import README, cli_commands, fenced_blocks

TOUR = "2-D tour: COCO results to calibrated boxes"


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("coco_cli")
    results, instances = synthetic_coco(300, seed=6)
    (work / "res.json").write_text(json.dumps(results))
    (work / "inst.json").write_text(json.dumps(instances))
    return work


def test_fit_then_calibrate(workdir):
    fit = detcal("fit", "res.json", "--gt", "inst.json", "--holdout", "0.3", "--quiet",
                 "--out", "p2d.json", cwd=workdir)
    assert fit.returncode == 0, fit.stderr
    assert "score calibrator:" in fit.stdout and "regions coverage" in fit.stdout
    profile = Profile2D.from_json((workdir / "p2d.json").read_text())
    assert profile.report["holdout"]["n_images"] == 90
    assert profile.provenance["options"]["holdout"] == 0.3
    cal = detcal("calibrate", "res.json", "--profile", "p2d.json", "--levels", "0.8", "0.9",
                 "--gt", "inst.json", "--out", "cal.json", cwd=workdir)
    assert cal.returncode == 0, cal.stderr
    records = json.loads((workdir / "cal.json").read_text())
    source = json.loads((workdir / "res.json").read_text())
    assert len(records) == len(source)
    assert [r["score_raw"] for r in records] == [r["score"] for r in source]
    assert {"region_0.8", "region_0.9"} <= set(records[0])
    back = read_coco_results(workdir / "cal.json")
    assert back.score.tolist() == [r["score"] for r in records]
    out = detcal("calibrate", "res.json", "--profile", "p2d.json", cwd=workdir)
    assert out.returncode == 0 and json.loads(out.stdout)[0]["region_0.95"]


@pytest.mark.parametrize(("args", "message"), [
    (("fit", "res.json", "--from", "kitti", "--gt", "inst.json"), "--from kitti"),
    (("fit", "res.json", "--from", "coco"), "--from coco needs --gt"),
    (("fit", "inst.json", "--gt", "inst.json"), "not a COCO results list"),
    (("fit", "res.json", "--gt", "inst.json", "--cov-source", "none"),
     "cov_source is an option of a 3-D fit"),
    (("fit", "res.json", "--gt", "inst.json", "--score-mode", "sigmoid"), "score_mode"),
    (("fit", "res.json", "--gt", "missing.json"), "missing.json: no such file"),
    (("fit", "inst.json", "--from", "coco", "--gt", "inst.json"), "results"),
    (("calibrate", "res.json", "--profile", "p2d.json", "--levels", "1.5"), "--levels"),
    (("calibrate", "res.json", "--profile", "p2d.json", "--nuscenes-gt", "inst.json"),
     "--nuscenes-gt does not apply"),
    (("evaluate", "res.json", "--profile", "p2d.json"), "2-D profile"),
])
def test_usage_errors_exit_2_with_one_line(workdir, args, message):
    if not (workdir / "p2d.json").exists():
        fit = detcal("fit", "res.json", "--gt", "inst.json", "--quiet", "--out", "p2d.json",
                     cwd=workdir)
        assert fit.returncode == 0, fit.stderr
    result = detcal(*args, cwd=workdir)
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert message in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_readme_2d_tour_runs(tmp_path: Path, monkeypatch):
    text = README.read_text(encoding="utf-8")
    section = text.split(f"\n## {TOUR}\n", 1)[1].split("\n## ", 1)[0]
    blocks = [b for b in fenced_blocks(section) if b.lang == "python"]
    assert len(blocks) == 1
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0].code, "README.md (2-D tour)", "exec"), {"__name__": "__main__"})
    commands = cli_commands(README, TOUR)
    assert [c[1] for c in commands] == ["fit", "calibrate"]
    for command in commands:
        result = detcal(*command[1:], cwd=tmp_path)
        assert result.returncode == 0, (command, result.stderr)
    assert json.loads((tmp_path / "calibrated.json").read_text())[0]["region_0.9"]
    # the tour's HTTP steps are docs/api.md's 2-D curl examples (the e2e docs tour runs those)
    api = (README.parent / "docs" / "api.md").read_text(encoding="utf-8")
    for line in ("-F coco_results=@coco_results.json -F coco_gt=@coco_instances.json",
                 '"profile": "cam2d", "levels": [0.8, 0.9],'):
        assert line in section and line in api
