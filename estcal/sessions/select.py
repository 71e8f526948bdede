"""Which parameters vary between sessions — decided on the training sessions only.

Forward selection over candidate parameters (default: the free joint offsets
and base parameters) by the REML likelihood-ratio test of a variance
component: adding ``q_j`` to the model, ``LR = −2ℓ_R(S) + 2ℓ_R(S ∪ {j})`` is
distributed under ``q_j = 0`` as the boundary mixture ½χ²₀ + ½χ²₁ (Self &
Liang 1987; Stram & Lee 1994), so ``p = ½ P(χ²₁ > LR)``; the best candidate is
added while ``p < α / (number of candidates screened)`` (Bonferroni). Each
screening step relinearises at the current fit (:func:`fit_sessions`).
"""
from __future__ import annotations


from .fit import fit_sessions

__all__ = ["choose_vary"]


def _default_candidates(fit) -> list:
    pv = fit.robot.params
    kinds = dict(zip(pv.names, pv.kinds))
    return [n for n in fit.names if kinds.get(n) in ("offset", "base")]


def choose_vary(robot, datasets, free, candidates=None, *, noise=None, alpha: float = 0.01, max_vary: int = 6,
                theta=None) -> dict:
    """Forward selection of the varying parameters; returns ``{"vary", "steps", "fit"}``.

    ``steps`` lists, per step, every candidate's LR statistic and p-value; needs at least
    two sessions (with one session there is no between-session information: ``vary = []``).
    """
    from scipy import stats

    fit = fit_sessions(robot, datasets, free, [], noise=noise, theta=theta)
    if len(datasets) < 2:
        return {"vary": [], "steps": [], "fit": fit, "note": "one session: no between-session information"}
    cands = list(candidates) if candidates is not None else _default_candidates(fit)
    vary, steps = [], []
    cur = fit
    for _ in range(max_vary):
        rest = [c for c in cands if c not in vary]
        if not rest:
            break
        table = []
        for c in rest:
            f = fit_sessions(robot, datasets, free, vary + [c], noise=noise, theta=cur.theta, max_iter=3)
            lr = max(cur.reml_objective - f.reml_objective, 0.0)
            table.append({"parameter": c, "lr": float(lr), "p_value": float(0.5 * stats.chi2.sf(lr, 1)),
                          "std": f.variance_components()[-1]})
        table.sort(key=lambda e: e["p_value"])
        best = table[0]
        ok = best["p_value"] < alpha / len(rest)
        steps.append({"table": table, "accepted": best["parameter"] if ok else None,
                      "alpha_per_test": alpha / len(rest)})
        if not ok:
            break
        vary.append(best["parameter"])
        cur = fit_sessions(robot, datasets, free, vary, noise=noise, theta=cur.theta)
    return {"vary": vary, "steps": steps, "fit": cur}
