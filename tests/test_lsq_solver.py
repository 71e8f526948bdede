"""The least-squares step and the BLAS thread guard of ``estcal.estimate.lsq``."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.base.blas import _blas_thread_setters, single_thread_blas
from estcal.estimate.lsq import _solve


@pytest.mark.parametrize("mu", [0.0, 1e-3, 10.0])
def test_step_matches_damped_normal_equations(mu):
    """x = argmin ‖A x − b‖² + μ‖S x‖² with S = diag(column norms) (damping on the scaled system)."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(60, 8)) * np.logspace(-4, 2, 8)  # badly scaled columns (m vs rad)
    b = rng.normal(size=60)
    s = np.linalg.norm(A, axis=0)
    x_ref = np.linalg.solve(A.T @ A + mu * np.diag(s**2), A.T @ b)
    np.testing.assert_allclose(_solve(A, b, mu), x_ref, rtol=1e-9, atol=1e-12)


def test_step_rank_deficient_falls_back_to_minimum_norm():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(30, 4))
    A = np.column_stack([A, A[:, 0]])  # duplicated column
    b = rng.normal(size=30)
    x = _solve(A, b)
    # minimum-norm solution of the scaled system splits the duplicated columns equally
    assert x[0] == pytest.approx(x[4], rel=1e-8)
    np.testing.assert_allclose(A @ x, A @ np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-10)


def test_single_thread_blas_restores_thread_counts():
    pairs = _blas_thread_setters()
    before = [int(get()) for get, _ in pairs]
    with single_thread_blas():
        assert all(int(get()) == 1 for get, _ in pairs)
        np.linalg.qr(np.ones((5, 3)))
    assert [int(get()) for get, _ in pairs] == before
