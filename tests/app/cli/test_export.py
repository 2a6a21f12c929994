"""`detcal export`: a profile JSON file or a stored profile to an ONNX / TorchScript file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.cli.main import main
from app.settings import Settings
from calibrators.data import synthetic_dump

ort = pytest.importorskip("onnxruntime")
torch = pytest.importorskip("torch")
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.:DeprecationWarning")


@pytest.fixture
def profile_file(tmp_path: Path, profile_json_given: str) -> Path:
    path = tmp_path / "profile.json"
    path.write_text(profile_json_given)
    return path


def test_export_a_profile_file_to_onnx(profile_file, tmp_path, capsys):
    out = tmp_path / "calibration.onnx"
    assert main(["export", str(profile_file), "--out", str(out), "--levels", "0.5", "0.9"]) == 0
    said = capsys.readouterr().err
    assert f"wrote {out}: onnx graph of {profile_file}" in said
    assert "inputs logits, boxes, ego_xy, covariances_raw" in said
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    meta = json.loads(session.get_modelmeta().custom_metadata_map["detcal"])
    assert meta["levels"] == [0.5, 0.9] and meta["cov_source"] == "given"
    dump = synthetic_dump(n_frames=3, seed=2)
    got = session.run(["scores", "radii"], {
        "logits": dump.det_logits[:, -1], "boxes": dump.final_boxes,
        "ego_xy": dump.ego_xy(dump.det_frame), "covariances_raw": dump.det_cov})
    assert got[0].shape == (dump.n_detections,) and got[1].shape == (dump.n_detections, 2)


@pytest.mark.parametrize("ref", ["lidar", "lidar@1", "layers"])
def test_export_a_stored_profile_to_torchscript(ref, seeded: Settings, tmp_path, capsys):
    out = tmp_path / "calibration.pt"
    code = main(["export", ref, "--data-dir", str(seeded.data_dir), "--format", "torchscript",
                 "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert f"torchscript graph of {ref.split('@')[0]}@1" in capsys.readouterr().err
    extra = {"detcal.json": ""}
    module = torch.jit.load(str(out), _extra_files=extra)
    meta = json.loads(extra["detcal.json"])
    assert meta["cov_source"] == ("layers" if ref == "layers" else "given")
    n = 4
    inputs = {"logits": np.zeros((n, len(meta["classes"]))), "boxes": np.ones((n, 9)),
              "layer_boxes": np.ones((n, 3, 9)), "ego_xy": np.zeros((n, 2)),
              "covariances_raw": np.broadcast_to(np.eye(2), (n, 2, 2)).copy()}
    res = module(*[torch.from_numpy(inputs[name]) for name in meta["inputs"]])
    assert list(res) == meta["outputs"] and res["scores"].shape == (n,)


@pytest.mark.parametrize("args, text", [
    (["lidar@7"], "profile 'lidar' has no version 7"),
    (["nope"], "profile 'nope' does not exist"),
    (["lidar@0"], "PROFILE: "),
    (["lidar", "--levels", "1.5"], r"levels\[0\] = 1.5"),
    (["lidar", "--cov-source", "layers"], "cov_source 'layers' is not served"),
    (["missing.json"], "missing.json: no such file"),
])
def test_export_errors_exit_2(args, text, seeded: Settings, tmp_path, capsys):
    import re

    out = tmp_path / "g.onnx"
    code = main(["export", *args, "--data-dir", str(seeded.data_dir), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("detcal export: error: ") and re.search(text, err), err
    assert not out.exists()


def test_export_without_a_store(tmp_path, capsys):
    code = main(["export", "lidar", "--data-dir", str(tmp_path / "none"), "--out",
                 str(tmp_path / "g.onnx")])
    assert code == 2 and "no profile store at" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_export_a_profile_by_alias(seeded: Settings, tmp_path, capsys):
    """`name@alias` resolves as the service resolves it (skipped where the store has no
    aliases)."""
    from app.store import Store

    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    if not hasattr(store, "set_alias"):
        store.close()
        pytest.skip("this store has no aliases")
    store.set_alias("lidar", "challenger", 1)
    store.close()
    out = tmp_path / "g.onnx"
    code = main(["export", "lidar@challenger", "--data-dir", str(seeded.data_dir), "--out",
                 str(out)])
    assert code == 0, capsys.readouterr().err
    assert "onnx graph of lidar@1" in capsys.readouterr().err and out.is_file()


@pytest.mark.parametrize("flag, value, text", [("--format", "tflite", "format must be one of"),
                                               ("--input-dtype", "float16", "input_dtype must")])
def test_bad_format_or_dtype(flag, value, text, profile_file, tmp_path, capsys):
    out = tmp_path / "g.onnx"
    assert main(["export", str(profile_file), flag, value, "--out", str(out)]) == 2
    assert text in capsys.readouterr().err and not out.exists()
