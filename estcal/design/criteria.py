"""Optimality criteria of calibration plans, vectorised over batches of plans.

Everything here is a pure function of the (weighted) information matrix

.. math::  M = \\sum_{i=1}^{m} J_i^T W_i J_i \\; (+\\, \\Sigma_{prior}^{-1}),
           \\qquad C = M^{-1},

where ``J_i`` (r × p) are the identification-Jacobian rows of pose ``i`` for the
``p`` free parameters and ``W_i = diag(σ_i^{-2})`` the measurement weights. ``C``
is the parameter covariance every estimator in estcal reports for the same
problem ((JᵀWJ)⁻¹ of least squares, (JᵀWJ + Σ₀⁻¹)⁻¹ of MAP / Kalman,
Mooring et al. (4.54), (4.70)). All functions accept ``M`` of shape
``(..., p, p)`` and return arrays of shape ``(...)`` so that thousands of plans
are scored with one batched eigen-decomposition.

Singular values ``s_1 ≥ … ≥ s_p`` used by the observability indices are those
of the *whitened* stacked Jacobian ``W^{1/2} J`` (``s_k = sqrt(λ_k(M))``); with
unit weights (``sigma=1``) they are the singular values of ``J`` itself.

Criteria (smaller is better unless marked ↑):

===============  ==============================================================
name             definition
===============  ==============================================================
``cond``         κ(J) = s_max / s_min (condition number of the Jacobian)
``cond_JtJ``     κ(JᵀJ) = (s_max / s_min)² — the textbook's "κ(J)" (Mooring 4.174)
``O1`` ↑         Borm–Menq (Π s_k)^{1/p} / √m  (Mooring 4.193–4.194)
``O2`` ↑         s_min / s_max
``O3`` ↑         s_min
``O4`` ↑         s_min² / s_max
``O5`` ↑         1 / Σ_k s_k⁻¹
``D``            det(C)^{1/p}
``A``            trace(C)
``E``            λ_max(C) = 1 / λ_min(M)
``G``            max over a set of test poses of trace(J_t C J_tᵀ)
``test-pose``    ρ0² = trace(J_0 C J_0ᵀ) (Klimchik eq. 14), mean or max over
                 a set of test poses
===============  ==============================================================

With ``C = σ² (Σ J_iᵀJ_i)⁻¹`` the test-pose value is Klimchik's
``ρ0² = σ² trace(J0 (Σ J_iᵀ J_i)⁻¹ J0ᵀ)``: the mean squared position error at
the test pose after compensation with the identified parameters. ``G`` is the
classical G-optimality (maximum prediction variance over the design region);
it equals the ``max`` form of the test-pose criterion evaluated on the design
region instead of user-chosen test poses.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = [
    "information_matrix", "covariance", "singular_values", "cond_J", "cond_JtJ",
    "o1", "o2", "o3", "o4", "o5", "d_criterion", "a_criterion", "e_criterion", "g_criterion",
    "test_pose_variance", "test_pose_criterion", "CRITERIA", "criterion_value", "criterion_loss",
    "evaluate_all", "PlanCriteria", "accuracy_map", "AccuracyMap", "normalise_criterion",
]

#: Relative eigenvalue threshold below which an information matrix is treated as singular.
RTOL = 1e-12


# ----------------------------------------------------------------- building M
def information_matrix(J_blocks, sigma=1.0, prior=None) -> np.ndarray:
    """Weighted information matrix ``M = Σ_i J_iᵀ W_i J_i (+ prior)``.

    Parameters
    ----------
    J_blocks : array (..., m, r, p)
        Jacobian rows of ``m`` poses (``r`` rows each) for ``p`` parameters; any
        leading axes are batch axes (several plans at once). A 2-D ``(rows, p)``
        stacked Jacobian is accepted as one pose with ``rows`` rows.
    sigma : float or array broadcastable to (..., m, r)
        Standard deviation of each row (same units as the row).
    prior : (p, p) array, optional
        Prior information ``Σ₀⁻¹`` added to the sum (MAP / Kalman, Mooring 4.70).

    Returns
    -------
    M : (..., p, p)
    """
    J = np.asarray(J_blocks, float)
    if J.ndim == 2:
        J = J[None]
    w = np.broadcast_to(1.0 / np.asarray(sigma, float) ** 2, J.shape[:-1])
    M = np.einsum("...mrp,...mr,...mrq->...pq", J, w, J, optimize=True)
    if prior is not None:
        M = M + np.asarray(prior, float)
    return M


def _eigh(M):
    M = np.asarray(M, float)
    M = 0.5 * (M + np.swapaxes(M, -1, -2))
    lam, V = np.linalg.eigh(M)
    return lam, V


def _singular_mask(lam):
    top = np.maximum(lam[..., -1], np.finfo(float).tiny)
    return lam[..., 0] <= RTOL * top


def covariance(M, allow_singular: bool = False) -> np.ndarray:
    """``C = M⁻¹`` for a batch of information matrices (eigen-decomposition).

    Raises ``numpy.linalg.LinAlgError`` naming the batch index when a matrix is
    singular (relative eigenvalue < 1e-12), unless ``allow_singular`` — then
    singular entries are filled with ``inf``.
    """
    lam, V = _eigh(M)
    sing = _singular_mask(lam)
    if np.any(sing) and not allow_singular:
        idx = np.argwhere(np.atleast_1d(sing))[0]
        raise np.linalg.LinAlgError(
            f"information matrix {tuple(idx) if np.ndim(sing) else ''} is singular: the plan does not "
            f"identify all free parameters (smallest/largest eigenvalue "
            f"{np.atleast_1d(lam[..., 0])[tuple(idx)] if np.ndim(sing) else lam[0]:.3g}/"
            f"{np.atleast_1d(lam[..., -1])[tuple(idx)] if np.ndim(sing) else lam[-1]:.3g})")
    inv = 1.0 / np.where(sing[..., None], 1.0, lam)
    C = np.einsum("...ik,...k,...jk->...ij", V, inv, V)
    if np.any(sing):
        C = np.where(sing[..., None, None], np.inf, C)
    return C


def singular_values(M) -> np.ndarray:
    """Singular values of the whitened stacked Jacobian, descending, from ``M = JᵀWJ``."""
    lam, _ = _eigh(M)
    return np.sqrt(np.clip(lam[..., ::-1], 0.0, None))


# ------------------------------------------------ eigenvalue-based criteria
def _eigvals(M):
    M = np.asarray(M, float)
    return np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, -1, -2)))


def _value_from_eigs(name, lam, m=None):
    """Criterion ``name`` from the ascending eigenvalues ``lam`` (..., p) of ``M``.

    ``s_k = sqrt(λ_k)`` are the singular values of the whitened Jacobian and
    ``1/λ_k`` the covariance eigenvalues. Singular matrices give ``inf`` for
    smaller-is-better criteria and 0 for the observability indices.
    """
    sing = _singular_mask(lam)
    safe = np.where(sing[..., None], 1.0, lam)
    lo, hi = safe[..., 0], safe[..., -1]
    if name == "D":
        v = np.exp(-np.mean(np.log(safe), axis=-1))
    elif name == "A":
        v = np.sum(1.0 / safe, axis=-1)
    elif name == "E":
        v = 1.0 / lo
    elif name == "cond":
        v = np.sqrt(hi / lo)
    elif name == "cond_JtJ":
        v = hi / lo
    elif name == "O1":
        v = np.exp(0.5 * np.mean(np.log(safe), axis=-1)) / np.sqrt(np.asarray(m, float))
    elif name == "O2":
        v = np.sqrt(lo / hi)
    elif name == "O3":
        v = np.sqrt(lo)
    elif name == "O4":
        v = lo / np.sqrt(hi)
    elif name == "O5":
        v = 1.0 / np.sum(1.0 / np.sqrt(safe), axis=-1)
    else:  # pragma: no cover - guarded by callers
        raise ValueError(name)
    return np.where(sing, 0.0 if CRITERIA[name][0] else np.inf, v)


def cond_J(M) -> np.ndarray:
    """κ(J) = s_max / s_min of the whitened stacked Jacobian (``inf`` if singular)."""
    return _value_from_eigs("cond", _eigvals(M))


def cond_JtJ(M) -> np.ndarray:
    """κ(JᵀJ) = (s_max / s_min)², the quantity the textbook tabulates as κ (Mooring 4.174)."""
    return _value_from_eigs("cond_JtJ", _eigvals(M))


def o1(M, m) -> np.ndarray:
    """Borm–Menq observability index O1 = (s_1 ··· s_p)^{1/p} / √m (↑ better; Mooring 4.193)."""
    return _value_from_eigs("O1", _eigvals(M), m)


def o2(M) -> np.ndarray:
    """O2 = s_min / s_max (inverse condition number, ↑ better)."""
    return _value_from_eigs("O2", _eigvals(M))


def o3(M) -> np.ndarray:
    """O3 = s_min (minimum singular value, ↑ better)."""
    return _value_from_eigs("O3", _eigvals(M))


def o4(M) -> np.ndarray:
    """O4 = s_min² / s_max (noise amplification index, ↑ better)."""
    return _value_from_eigs("O4", _eigvals(M))


def o5(M) -> np.ndarray:
    """O5 = 1 / Σ_k s_k⁻¹ (↑ better)."""
    return _value_from_eigs("O5", _eigvals(M))


def d_criterion(M) -> np.ndarray:
    """D = det(C)^{1/p} = det(M)^{-1/p} (geometric mean of the covariance eigenvalues)."""
    return _value_from_eigs("D", _eigvals(M))


def a_criterion(M) -> np.ndarray:
    """A = trace(C) (sum of the parameter variances)."""
    return _value_from_eigs("A", _eigvals(M))


def e_criterion(M) -> np.ndarray:
    """E = λ_max(C) = 1 / λ_min(M) (largest parameter-space variance)."""
    return _value_from_eigs("E", _eigvals(M))


def test_pose_variance(M, J0) -> np.ndarray:
    """Per-test-pose prediction variance ``trace(J0_k C J0_kᵀ)``.

    Parameters
    ----------
    M : (..., p, p) information matrices.
    J0 : (K, r, p) or (r, p) prediction Jacobians of the test poses (e.g. tool
        position rows). With ``C`` in parameter units², the result is in output
        units² (m² for position rows).

    Returns
    -------
    (..., K) array (``inf`` where ``M`` is singular).
    """
    J0 = np.asarray(J0, float)
    if J0.ndim == 2:
        J0 = J0[None]
    C = covariance(M, allow_singular=True)
    finite = np.all(np.isfinite(C), axis=(-1, -2))
    Cf = np.where(finite[..., None, None], C, 0.0)
    # trace(J C Jᵀ) = Σ_{r,p,q} J_rp C_pq J_rq
    v = np.einsum("krp,...pq,krq->...k", J0, Cf, J0, optimize=True)
    return np.where(finite[..., None], v, np.inf)


def test_pose_criterion(M, J0, aggregate: str = "mean") -> np.ndarray:
    """Klimchik's test-pose criterion ρ0² = trace(J0 C J0ᵀ) (eq. 14).

    For one test pose this is the expected squared position error at ``q0``
    after compensation; for a set of poses / a path, ``aggregate`` is ``'mean'``
    (average ρ0² along the path) or ``'max'`` (worst pose).
    """
    v = test_pose_variance(M, J0)
    if aggregate == "mean":
        return v.mean(axis=-1)
    if aggregate == "max":
        return v.max(axis=-1)
    raise ValueError(f"aggregate must be 'mean' or 'max', got {aggregate!r}")


def g_criterion(M, J_test) -> np.ndarray:
    """G = max_k trace(J_k C J_kᵀ) over a set of test poses (the design region)."""
    return test_pose_criterion(M, J_test, "max")


# ---------------------------------------------------------------- dispatch
#: name -> (larger_is_better, needs_test_jacobian, description)
CRITERIA = {
    "D": (False, False, "det(C)^(1/p)"),
    "A": (False, False, "trace(C)"),
    "E": (False, False, "lambda_max(C)"),
    "G": (False, True, "max_k trace(J_k C J_k^T) over the test set"),
    "O1": (True, False, "(prod s)^(1/p)/sqrt(m) (Borm-Menq)"),
    "O2": (True, False, "s_min/s_max"),
    "O3": (True, False, "s_min"),
    "O4": (True, False, "s_min^2/s_max"),
    "O5": (True, False, "1/sum(1/s)"),
    "cond": (False, False, "kappa(J) = s_max/s_min"),
    "cond_JtJ": (False, False, "kappa(J^T J) = (s_max/s_min)^2"),
    "test-pose": (False, True, "rho0^2 = trace(J0 C J0^T) (Klimchik 14), mean over test poses"),
    "test-pose-max": (False, True, "rho0^2 = trace(J0 C J0^T), max over test poses"),
}

_ALIASES = {"d": "D", "a": "A", "e": "E", "g": "G", "o1": "O1", "o2": "O2", "o3": "O3", "o4": "O4",
            "o5": "O5", "cond": "cond", "cond_j": "cond", "condj": "cond", "cond_jtj": "cond_JtJ",
            "condjtj": "cond_JtJ", "test-pose": "test-pose", "test_pose": "test-pose", "testpose": "test-pose",
            "rho0": "test-pose", "test-pose-max": "test-pose-max", "test_pose_max": "test-pose-max"}


def normalise_criterion(name: str) -> str:
    """Canonical criterion name (case-insensitive; ``test_pose`` → ``test-pose``)."""
    key = _ALIASES.get(str(name).strip().lower())
    if key is None:
        raise ValueError(f"unknown criterion {name!r}; choose one of {sorted(CRITERIA)}")
    return key


def criterion_value(name: str, M, m=None, J_test=None) -> np.ndarray:
    """Value of criterion ``name`` for information matrices ``M`` (..., p, p).

    ``m`` (number of poses) is needed by O1; ``J_test`` (K, r, p) by ``G`` and
    the test-pose criteria.
    """
    name = normalise_criterion(name)
    if CRITERIA[name][1] and J_test is None:
        raise ValueError(f"criterion {name!r} needs test-pose Jacobians (J_test)")
    if name == "O1" and m is None:
        raise ValueError("criterion 'O1' needs the number of poses m")
    if name == "G":
        return g_criterion(M, J_test)
    if name == "test-pose":
        return test_pose_criterion(M, J_test, "mean")
    if name == "test-pose-max":
        return test_pose_criterion(M, J_test, "max")
    return _value_from_eigs(name, _eigvals(M), m)


def larger_is_better(name: str) -> bool:
    return CRITERIA[normalise_criterion(name)][0]


def criterion_loss(name: str, M, m=None, J_test=None) -> np.ndarray:
    """Scalar(s) to *minimise* for criterion ``name``, finite even for singular ``M``.

    A monotone transform of :func:`criterion_value` (so both have the same
    optimum): ``log(value)`` for smaller-is-better criteria, ``−log(value)``
    for the ↑ indices. Singular matrices get a large finite loss
    (1e6 − log(λ_min/λ_max)) so that local optimisers can walk away from them.
    """
    name = normalise_criterion(name)
    M = np.asarray(M, float)
    lam = _eigvals(M)
    sing = _singular_mask(lam)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if CRITERIA[name][1]:
            v = criterion_value(name, M, m, J_test)
        else:
            if name == "O1" and m is None:
                raise ValueError("criterion 'O1' needs the number of poses m")
            v = _value_from_eigs(name, lam, m)
        out = -np.log(v) if larger_is_better(name) else np.log(v)
        rel = np.clip(lam[..., 0], 1e-300, None) / np.maximum(lam[..., -1], 1e-300)
        pen = 1e6 - np.log(rel)
    bad = sing | ~np.isfinite(out)
    return np.where(bad, pen, out)


# ---------------------------------------------------------------- reports
@dataclass
class PlanCriteria:
    """All criteria of one plan (see module docstring for definitions and units)."""

    m: int
    p: int
    singular_values: list
    cond: float
    cond_JtJ: float
    O1: float
    O2: float
    O3: float
    O4: float
    O5: float
    D: float
    A: float
    E: float
    G: float | None = None
    test_pose: float | None = None
    test_pose_max: float | None = None
    param_std: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        rows = [f"plan of m={self.m} poses, p={self.p} parameters"]
        for k in ("cond", "cond_JtJ", "O1", "O2", "O3", "O4", "O5", "D", "A", "E", "G", "test_pose",
                  "test_pose_max"):
            v = getattr(self, k)
            if v is not None:
                rows.append(f"  {k:<14}{v:.6g}")
        return "\n".join(rows)


def evaluate_all(M, m: int, J_test=None, names=None) -> PlanCriteria:
    """Every criterion of one plan with information matrix ``M`` (p, p)."""
    M = np.asarray(M, float)
    s = singular_values(M)
    C = covariance(M, allow_singular=True)
    lam = _eigvals(M)
    val = {k: float(_value_from_eigs(k, lam, m)) for k in ("cond", "cond_JtJ", "O1", "O2", "O3", "O4", "O5",
                                                           "D", "A", "E")}
    std = np.sqrt(np.diag(C)) if np.all(np.isfinite(C)) else np.full(M.shape[0], np.inf)
    out = PlanCriteria(
        m=int(m), p=int(M.shape[0]), singular_values=s.tolist(), **val,
        param_std={n: float(v) for n, v in zip(names or [f"p{i}" for i in range(len(std))], std)})
    if J_test is not None:
        v = test_pose_variance(M, J_test)
        out.G = float(np.max(v))
        out.test_pose = float(np.mean(v))
        out.test_pose_max = float(np.max(v))
    return out


@dataclass
class AccuracyMap:
    """Expected position error after calibration over a grid of poses.

    ``std`` is sqrt(trace(J_k C J_kᵀ)) — the RMS distance error (m) — and
    ``std_xyz`` the per-axis standard deviations (m) at each pose ``q`` whose
    nominal tool position is ``xyz``.
    """

    q: np.ndarray
    xyz: np.ndarray
    std: np.ndarray
    std_xyz: np.ndarray

    def summary(self) -> dict:
        return {"n": int(len(self.std)), "mean_m": float(np.mean(self.std)), "max_m": float(np.max(self.std)),
                "min_m": float(np.min(self.std)), "median_m": float(np.median(self.std))}

    def to_dict(self) -> dict:
        return {"q": self.q.tolist(), "xyz": self.xyz.tolist(), "std": self.std.tolist(),
                "std_xyz": self.std_xyz.tolist(), "summary": self.summary()}

    def __str__(self) -> str:
        s = self.summary()
        return (f"accuracy map over {s['n']} poses: expected position error std mean {s['mean_m'] * 1e3:.4g} mm, "
                f"max {s['max_m'] * 1e3:.4g} mm, min {s['min_m'] * 1e3:.4g} mm")


def accuracy_map(C, J_pos, q=None, xyz=None) -> AccuracyMap:
    """Expected position-error standard deviation at each pose of a region.

    Parameters
    ----------
    C : (p, p) parameter covariance (e.g. from a plan or an estimator).
    J_pos : (K, 3, p) position Jacobians of the grid poses w.r.t. the same parameters.
    q, xyz : (K, n), (K, 3) grid joint values and nominal positions (stored for plotting).
    """
    C = np.asarray(C, float)
    J = np.asarray(J_pos, float)
    cov_xyz = np.einsum("krp,pq,ksq->krs", J, C, J, optimize=True)  # (K, 3, 3)
    var = np.einsum("kii->ki", cov_xyz)
    K = J.shape[0]
    return AccuracyMap(q=np.zeros((K, 0)) if q is None else np.asarray(q, float),
                       xyz=np.zeros((K, 3)) if xyz is None else np.asarray(xyz, float),
                       std=np.sqrt(var.sum(-1)), std_xyz=np.sqrt(var))
