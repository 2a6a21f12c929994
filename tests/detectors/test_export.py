"""Exported graphs (torch, TorchScript, ONNX via onnxruntime) agree with the library to 1e-6.

Every case of `export_cases.CASES` runs as a torch module and as a saved and reloaded
TorchScript module; the cases marked `onnx` (one per score, covariance and region module, both
input dtypes) are also written as ONNX and run with onnxruntime. Inputs are the shipped lidar
validation dump, dumps of the shipped radar1, radar5 and camera detectors, and synthetic dumps.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from detectors.export import build_graph, export_profile
from detectors.export.writers import METADATA_KEY
from tests.detectors.export_cases import (
    CASES,
    LEVELS,
    TOLERANCE,
    Case,
    arrays,
    build_dumps,
    case_profile,
    differences,
    graph_inputs,
    library,
)

ort = pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")
# TorchScript is deprecated upstream (torch 2.9+) but is the format asked for.
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.:DeprecationWarning")


@pytest.fixture(scope="module")
def dumps():
    return build_dumps()


@pytest.fixture(scope="module")
def profiles(dumps):
    cache: dict[tuple, object] = {}

    def get(case: Case):
        key = (case.dump, json.dumps(case.options, sort_keys=True), str(case.profile_file))
        if key not in cache:
            cache[key] = case_profile(case, dumps[case.dump])
        return cache[key]

    return get


def _setup(case: Case, dumps, profiles):
    profile = profiles(case)
    source = case.source or profile.cov_source
    values = arrays(dumps[case.dump], case.dtype)
    lib = library(profile, values, source, bool(profile.modulation or case.layer_logits))
    return profile, source, values, lib


def _check(diffs: dict[str, tuple[float, float]], case: Case) -> None:
    worst = {name: gap for name, (gap, _) in diffs.items() if gap > TOLERANCE}
    assert not worst, f"{case.id}: {worst}"


def _run_onnx(path, names, values):
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    out = session.run(None, dict(zip(names, graph_inputs(names, values), strict=True)))
    return dict(zip([o.name for o in session.get_outputs()], out, strict=True))


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_torch_and_torchscript_agree_with_the_library(case, dumps, profiles, tmp_path):
    profile, source, values, lib = _setup(case, dumps, profiles)
    graph = build_graph(profile, cov_source=source, levels=LEVELS,
                        layer_logits=case.layer_logits)
    tensors = [torch.from_numpy(a) for a in graph_inputs(graph.input_names, values)]
    eager = {k: v.numpy() for k, v in graph(*tensors).items()}
    assert list(eager) == graph.output_names
    _check(differences(eager, lib), case)

    meta = export_profile(profile, tmp_path / "g.pt", "torchscript", cov_source=source,
                          levels=LEVELS, layer_logits=case.layer_logits)
    extra = {f"{METADATA_KEY}.json": ""}
    scripted = torch.jit.load(str(tmp_path / "g.pt"), _extra_files=extra)
    assert json.loads(extra[f"{METADATA_KEY}.json"]) == meta
    out = {k: v.numpy() for k, v in scripted(*tensors).items()}
    _check(differences(out, lib), case)
    assert profile.schema_version == (1 if case.id.startswith("v1") else 2)


ONNX_CASES = [c for c in CASES if c.onnx]


@pytest.fixture(scope="module")
def onnx_files(dumps, profiles, tmp_path_factory):
    """Each ONNX case written once: `{case id: (path, metadata)}`."""
    folder = tmp_path_factory.mktemp("onnx")
    out = {}
    for case in ONNX_CASES:
        profile = profiles(case)
        path = folder / f"{case.id}.onnx"
        meta = export_profile(profile, path, "onnx", cov_source=case.source, levels=LEVELS,
                              layer_logits=case.layer_logits, input_dtype=case.dtype)
        out[case.id] = (path, meta)
    return out


@pytest.mark.parametrize("case", ONNX_CASES, ids=[c.id for c in ONNX_CASES])
def test_onnx_agrees_with_the_library(case, dumps, profiles, onnx_files):
    profile, source, values, lib = _setup(case, dumps, profiles)
    path, meta = onnx_files[case.id]
    out = _run_onnx(path, meta["inputs"], values)
    assert list(out) == meta["outputs"]
    assert all(out[k].dtype == np.float64 for k in out if k not in ("labels", "region_group"))
    _check(differences(out, lib), case)
    model = onnx.load(str(path))
    assert json.loads({p.key: p.value for p in model.metadata_props}[METADATA_KEY]) == meta
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    dtype = {"float64": "tensor(double)", "float32": "tensor(float)"}[case.dtype]
    assert [(i.name, i.type) for i in session.get_inputs()] == [(n, dtype)
                                                                for n in meta["inputs"]]


@pytest.mark.parametrize("n", [0, 1, 2])
def test_any_number_of_detections(n, dumps, profiles, onnx_files, tmp_path):
    """N = 0, 1, 2 through ONNX and TorchScript: outputs shaped [N, ...], the library's for
    N >= 1 (the library itself refuses N = 0: its finiteness check cannot reshape [0])."""
    case = CASES[0]
    profile, source, values, _ = _setup(case, dumps, profiles)
    few = {k: None if v is None else v[:n] for k, v in values.items()}
    path, meta = onnx_files[case.id]
    export_profile(profile, tmp_path / "g.pt", "torchscript", levels=LEVELS)
    scripted = torch.jit.load(str(tmp_path / "g.pt"))
    res = scripted(*[torch.from_numpy(a) for a in graph_inputs(meta["inputs"], few)])
    outs = [_run_onnx(path, meta["inputs"], few), {k: v.numpy() for k, v in res.items()}]
    for out in outs:
        assert out["scores"].shape == (n,) and out["radii"].shape == (n, len(LEVELS))
        assert out["covariances"].shape == (n, 2, 2) and out["region_group"].shape == (n,)
        if n:
            _check(differences(out, library(profile, few, source, profile.modulation)), case)


def test_region_groups_are_described(dumps, profiles, onnx_files):
    """`region_group` indexes the metadata's conformal groups: each group's class and distance
    range hold the detections it serves."""
    case = CASES[0]
    profile, source, values, lib = _setup(case, dumps, profiles)
    path, meta = onnx_files[case.id]
    out = _run_onnx(path, meta["inputs"], values)
    groups = meta["region_groups"]
    for label, d, g in zip(lib.labels, lib.distances, out["region_group"], strict=True):
        group = groups[g]
        assert group["class"] in (None, profile.classes[label])
        lo, hi = group["distance_range"]
        assert lo <= d and (hi is None or d < hi)


STANDALONE = """
import sys
for name in ("calibrators", "detectors", "app", "tests"):
    sys.modules[name] = None          # any import of detcal now fails
import json
import numpy as np
import onnxruntime as ort
import torch

inputs = dict(np.load("inputs.npz"))
session = ort.InferenceSession("g.onnx", providers=["CPUExecutionProvider"])
names = json.loads(session.get_modelmeta().custom_metadata_map["detcal"])["inputs"]
onnx_out = session.run(None, {n: inputs[n] for n in names})
extra = {"detcal.json": ""}
module = torch.jit.load("g.pt", _extra_files=extra)
order = json.loads(extra["detcal.json"])["inputs"]
script_out = module(*[torch.from_numpy(inputs[n]) for n in order])
np.savez("out.npz", **{"onnx_" + o.name: v for o, v in zip(session.get_outputs(), onnx_out)},
         **{"ts_" + k: v.numpy() for k, v in script_out.items()})
"""


def test_exported_graphs_run_without_detcal(dumps, profiles, onnx_files, tmp_path):
    """A fresh interpreter in which importing detcal fails runs both files."""
    import subprocess
    import sys

    case = CASES[0]
    profile, source, values, lib = _setup(case, dumps, profiles)
    path, meta = onnx_files[case.id]
    (tmp_path / "g.onnx").write_bytes(path.read_bytes())
    export_profile(profile, tmp_path / "g.pt", "torchscript", levels=LEVELS)
    np.savez(tmp_path / "inputs.npz", **{n: values[n] for n in meta["inputs"]})
    result = subprocess.run([sys.executable, "-c", STANDALONE], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    saved = np.load(tmp_path / "out.npz")
    for prefix in ("onnx_", "ts_"):
        out = {k[len(prefix):]: saved[k] for k in saved.files if k.startswith(prefix)}
        _check(differences(out, lib), case)
