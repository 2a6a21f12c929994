"""calibrators.core.checks: the covariance test's rounding allowance scales with the matrix."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.core.checks import check_covariances, covariance_tolerance
from calibrators.core.errors import FieldError
from calibrators.data import Dump


def rank_one(v, dtype=np.float64) -> np.ndarray:
    v = np.asarray(v, dtype=dtype)
    return np.outer(v, v)[None]


@pytest.mark.parametrize("scale", [1e-12, 1.0, 1e200, 1e300])
@pytest.mark.parametrize("v", [(1.0, 1.0), (0.3, 0.7), (1.0, -3e-5), (0.2, 0.5, -0.9)])
def test_rank_one_psd_matrices_pass_at_any_scale(v, scale):
    check_covariances("cov", rank_one(v) * scale)


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1.0, 1e200])
def test_indefinite_matrices_fail_at_any_scale(scale):
    with pytest.raises(FieldError, match=r"cov\[0\] is not positive semi-definite") as err:
        check_covariances("cov", np.array([[[1.0, 2.0], [2.0, 1.0]]]) * scale)
    assert err.value.field == "cov" and err.value.row == 0
    # no absolute floor: a tiny indefinite matrix is as indefinite as a large one
    with pytest.raises(FieldError, match="is not symmetric"):
        check_covariances("cov", np.array([[[1.0, 0.5], [0.0, 1.0]]]) * scale)


def test_float32_rounding_is_allowed_through_a_dump():
    """The issue's case: a float32 PSD covariance whose smallest eigenvalue comes out a few
    1e-9 below zero (refused as `det_cov[i] is not positive semi-definite` before)."""
    rng = np.random.default_rng(0)
    v = rng.normal(0, 0.5, (200, 2)).astype(np.float32)
    cov = np.einsum("ni,nj->nij", v, v).astype(np.float32)  # rank 1, rounded to float32
    eig_min = np.linalg.eigvalsh(cov.astype(np.float64))[:, 0]
    assert eig_min.min() < -1e-9  # what the old absolute tolerance refused
    check_covariances("det_cov", cov)
    check_covariances("det_cov", cov.astype(np.float64))  # float32 numbers in a float64 array
    n = len(cov)
    dump = Dump(classes=("car",), score_mode="sigmoid", frame_ids=np.array(["a"]),
                det_frame=np.zeros(n, dtype=int), det_logits=np.zeros((n, 1, 1)),
                det_boxes=np.zeros((n, 1, 9)), gt_frame=np.zeros(0, dtype=int),
                gt_labels=np.zeros(0, dtype=int), gt_boxes=np.zeros((0, 9)), det_cov=cov)
    assert dump.det_cov.dtype == np.float64


def test_tolerance_is_relative_and_follows_the_dtype():
    eps32, eps16 = float(np.finfo(np.float32).eps), float(np.finfo(np.float16).eps)
    tol = covariance_tolerance(np.array([1.0, 1e200, 0.0]), 2)
    np.testing.assert_allclose(tol, [16 * eps32, 16e200 * eps32, 0.0])
    assert covariance_tolerance(np.array([1.0]), 2, np.float16)[0] == 16 * eps16
    # just beyond the allowance is refused, just within it passes
    cov = np.array([[[1.0, 0.0], [0.0, 0.0]]])
    cov[0, 1, 1] = -0.5 * tol[0]
    check_covariances("cov", cov)
    cov[0, 1, 1] = -2.0 * tol[0]
    with pytest.raises(FieldError, match="not positive semi-definite"):
        check_covariances("cov", cov)
