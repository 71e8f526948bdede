"""Measurement noise from the data: variance components per measurement kind and axis (REML).

A camera measures depth worse than the lateral directions; a motion-capture system has its
own per-axis noise; positions and orientations differ in kind and unit. Instead of one
assumed σ, the residual of the fitted model is split into classes c (``position_x``,
``position_y``, ``position_z``, ``orientation_x`` … — the axes of the measuring frame, the
frame the data are expressed in) with one variance σ²_c each, estimated by restricted
maximum likelihood (Patterson & Thompson 1971), which accounts for the p fitted parameters
(plain residual variances are biased low by the fraction p/M)::

    r = A δ + ε,   ε ~ N(0, V),   V = diag(σ²_{c(i)})
    −2ℓ_R(σ²) = Σ_i log σ²_{c(i)} + log|AᵀV⁻¹A| + rᵀ(V⁻¹ − V⁻¹A(AᵀV⁻¹A)⁻¹AᵀV⁻¹) r

(the same restricted likelihood as the between-session variance components of
:mod:`estcal.sessions.system`, here with a diagonal V). With per-row noise
(``NoiseModel.row_sigma``, e.g. a marker std column) the class variance multiplies each row's
own relative σ: V_ii = f²_{c(i)} s_i², s_i = σ_i / median of σ over the class, so that σ_c = f_c
is the noise of a row at the class's median σ. Minimised over log σ² (L-BFGS-B);
standard errors from the observed information (numerical Hessian of −ℓ_R in σ²).
Residuals from unmodelled structure inflate the estimate: it is the noise *of this model*,
which is what its weights need; the error budget says how much of it is structure.
"""
from __future__ import annotations

import numpy as np

__all__ = ["reml_variance_components", "measurement_noise", "noise_lines"]

AXES = "xyz"
#: floor of a class's starting variance (a class of exact zeros) and the half-width of the search in log σ²
V_FLOOR = 1e-200
LOG_SPAN = 30.0


def _neg2ll(logv, A, r, cls, C, s2=1.0):
    v = np.exp(logv)[cls] * s2
    w = 1.0 / v
    Aw = A * w[:, None]
    N = A.T @ Aw
    try:
        L = np.linalg.cholesky(N)
    except np.linalg.LinAlgError:
        return 1e30
    g = Aw.T @ r
    z = np.linalg.solve(L, g)
    quad = float(r @ (w * r) - z @ z)
    return float(np.sum(np.log(v)) + 2 * np.sum(np.log(np.diag(L))) + quad)


def reml_variance_components(A, r, classes, names=None, scale=None) -> dict:
    """REML variances of the residual classes of the module docstring.

    Parameters
    ----------
    A : (M, p) Jacobian of the fitted parameters (any consistent scaling); r : (M,) residual.
    classes : (M,) integer class of each row; names : class names (default ``class<c>``).
    scale : optional (M,) relative std of each row within its class (V_ii = σ²_c · scale_i²).

    Returns
    -------
    ``{name: {"std": σ_c, "std_se": its standard error, "n_rows": rows}}`` (units of ``r``).
    """
    from scipy.optimize import minimize

    A = np.asarray(A, float)
    r = np.asarray(r, float)
    lab, cls = np.unique(np.asarray(classes), return_inverse=True)
    C = len(lab)
    names = list(names) if names is not None else [f"class{c}" for c in lab]
    # column scaling keeps AᵀV⁻¹A well conditioned (mixed metre / radian columns)
    s = np.linalg.norm(A, axis=0)
    s[s == 0] = 1.0
    A = A / s
    s2 = 1.0 if scale is None else np.asarray(scale, float) ** 2
    v0 = np.array([max(np.mean((r ** 2 / s2)[cls == c] if scale is not None else r[cls == c] ** 2), V_FLOOR)
                   for c in range(C)])
    # bounded search in log σ²: unbounded, L-BFGS-B's first line searches try exp(±700) — overflow to inf and
    # a division by zero in V⁻¹ (the RuntimeWarnings of the test run) — for a variance that the data put within
    # a factor e^±LOG_SPAN of the plain residual variance anyway
    bounds = [(lv - LOG_SPAN, lv + LOG_SPAN) for lv in np.log(v0)]
    res = minimize(_neg2ll, np.log(v0), args=(A, r, cls, C, s2), method="L-BFGS-B", bounds=bounds)
    v = np.exp(res.x)
    # observed information in σ² (central differences of −ℓ_R = ½ · neg2ll)
    h = 1e-4
    H = np.zeros((C, C))
    f = lambda lv: 0.5 * _neg2ll(lv, A, r, cls, C, s2)  # noqa: E731
    for a in range(C):
        for b in range(a, C):
            e_a, e_b = np.eye(C)[a] * h, np.eye(C)[b] * h
            H[a, b] = H[b, a] = (f(res.x + e_a + e_b) - f(res.x + e_a - e_b) - f(res.x - e_a + e_b)
                                 + f(res.x - e_a - e_b)) / (4 * h * h)
    try:
        cov_log = np.linalg.inv(H)
        se_v = np.sqrt(np.maximum(np.diag(cov_log), 0)) * v  # d σ² = σ² d log σ²
    except np.linalg.LinAlgError:
        se_v = np.full(C, np.nan)
    std = np.sqrt(v)
    return {names[c]: {"std": float(std[c]), "std_se": float(se_v[c] / (2 * std[c])),
                       "n_rows": int(np.sum(cls == c))} for c in range(C)}


def measurement_noise(problem, theta, free, by_axis: bool = True) -> dict:
    """Noise std per measurement kind (and axis of the measuring frame) of a fitted problem, by REML.

    Position rows are split by axis (x, y, z of the frame the data are expressed in),
    orientation rows likewise; other rows form one class per kind. Returns
    :func:`reml_variance_components` with keys ``position_x_mm`` … (mm) and ``orientation_x_mrad`` …
    (mrad), plus ``"estimated"``: a sentence saying what was estimated.
    """
    rows = problem.evaluate(np.asarray(theta, float))
    idx = problem.params.indices(list(free))
    A, r = rows.H[:, idx], rows.e
    kind = np.asarray(rows.kind)
    axis = np.zeros(len(r), int)
    for kd in (0, 1):
        m = np.flatnonzero(kind == kd)
        if by_axis and len(m):
            # rows of one kind come in (x, y, z) triples per measured point or frame
            axis[m] = np.arange(len(m)) % 3
    labels = np.array([f"{('position', 'orientation', 'scalar')[min(k, 2)]}"
                       + (f"_{AXES[a]}" if by_axis and k in (0, 1) else "") for k, a in zip(kind, axis)])
    names, cls = np.unique(labels, return_inverse=True)
    sig = np.asarray(rows.sigma, float)
    med = np.array([np.median(sig[cls == c]) for c in range(len(names))])
    rel = sig / med[cls]
    weighted = not np.allclose(rel, 1.0)
    comps = reml_variance_components(A, r, cls, names, scale=rel if weighted else None)
    out = {}
    for n, c in comps.items():
        unit, f = ("mrad", 1e3) if n.startswith("orientation") else ("mm", 1e3)
        out[f"{n}_{unit}"] = {"std": c["std"] * f, "std_se": c["std_se"] * f, "n_rows": c["n_rows"]}
    out["estimated"] = (f"noise std per {'kind and axis of the measuring frame' if by_axis else 'kind'} by REML "
                        f"from the residual of the {len(idx)}-parameter fit ({len(r)} rows)"
                        + ("; rows weighted by their own σ (per-row noise column), std = a row at the class's "
                           "median σ" if weighted else "")
                        + "; it holds the model error left in the residual, not only the instrument")
    return out


def noise_lines(d: dict) -> list[str]:
    """Text lines of :func:`measurement_noise`'s result (the commands' output)."""
    if not any(isinstance(v, dict) for v in d.values()):
        return [f"measurement noise: {d.get('estimated', 'not estimated')}"]
    parts = [f"{k.rsplit('_', 1)[0].replace('_', ' ')} {v['std']:.3g} ± {v['std_se']:.2g} {k.rsplit('_', 1)[1]}"
             for k, v in d.items() if isinstance(v, dict)]
    return [f"measurement noise (REML, per axis of the measuring frame): {', '.join(parts)}", f"  ({d['estimated']})"]
