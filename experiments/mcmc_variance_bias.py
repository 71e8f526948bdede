"""Is the emcee posterior σ of :func:`estcal.estimate.mcmc.sample_posterior` biased? (docs/mcmc-variance.md)

1. **Linear-Gaussian target with a known posterior.** The PUMA 560 problem (``--poses`` full
   poses, CMM noise 0.05 mm / 0.5 mrad) linearised at the LM optimum, e(θ) = e₀ − H(θ − θ̂),
   is sampled through the same code path (LogPosterior, moves, stopping rule); its posterior is
   exactly N(μ, C), C = (HᵀWH + diag(s⁻²))⁻¹ (s = prior std). Reported per seed: mean over
   the 30 whitened coordinates z = C^{-½}(θ − μ) of z² (exactly 1), with its τ-corrected
   Monte-Carlo standard error (:func:`mean_z2`).
2. **Nonlinear PUMA case against LM:** σ_MCMC/σ_LM (Laplace) per parameter, mean over the
   parameters, and E[z²] with z whitened by the LM covariance.

Each is run with the walkers started as draws from the Laplace approximation shrunk by
``init_scale`` — 0.5 (the former default) and 1 (the current default).

Usage: ``python experiments/mcmc_variance_bias.py [--quick] [--seeds N] [--json PATH]``
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.estimate._common import resolve_free  # noqa: E402
from estcal.estimate.lsq import calibrate_lsq  # noqa: E402
from estcal.estimate.mcmc import sample_posterior  # noqa: E402
from estcal.estimate.testproblems import simulated_problem  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402


class _Rows:
    def __init__(self, e, sigma):
        self.e, self.sigma = e, sigma


class LinearProblem:
    """e(θ) = e₀ − H (θ − θ̂): the Gaussian linearisation of a real problem (problem-like object)."""

    def __init__(self, problem, theta_hat):
        r = problem.evaluate(theta_hat, jacobian=True)
        self.params, self.terms = problem.params, []
        self.H, self.e0, self.sigma, self.theta_hat = r.H, r.e, r.sigma, np.asarray(theta_hat, float)

    def evaluate(self, theta, jacobian=False):
        return _Rows(self.evaluate_many(theta)[0], self.sigma)

    def evaluate_many(self, TH):
        return self.e0 - (np.atleast_2d(TH) - self.theta_hat) @ self.H.T


def linear_gaussian(problem, prior_std=0.1):
    """(linear problem, LM result, exact posterior mean, exact posterior covariance)."""
    lm = calibrate_lsq(problem)
    problem, fidx, _ = resolve_free(problem)
    th = problem.params.values.copy()
    th_hat = th.copy()
    th_hat[fidx] = lm.estimate
    lin = LinearProblem(problem, th_hat)
    A = lin.H[:, fidx] / lin.sigma[:, None]
    P = A.T @ A + np.eye(fidx.size) / prior_std ** 2
    # minimiser of |e₀/σ − A(x − x̂)|² + |(x − x₀)/s|²
    mean = np.linalg.solve(P, A.T @ (A @ lm.estimate + lin.e0 / lin.sigma) + th[fidx] / prior_std ** 2)
    return lin, lm, mean, np.linalg.inv(P)


def mean_z2(Z):
    """Mean over coordinates and draws of z² (1 for the exact target) and its Monte-Carlo SE.

    An independence-MH rejection freezes every coordinate of a walker at once, so the per-
    coordinate errors are correlated: average over coordinates first (u = mean_j z_j² per walker
    and step), then SE = sd(u) √(τ_u / (steps · walkers)) with τ_u from emcee.autocorr."""
    import emcee

    u = (Z ** 2).mean(2)
    tau_u = float(emcee.autocorr.integrated_time(u[:, :, None], tol=0, quiet=True)[0])
    return float(u.mean()), float(u.std(ddof=1) * np.sqrt(tau_u / u.size))


def whitened(X, mean, C):
    L = np.linalg.cholesky(C)
    sh = X.shape
    return np.linalg.solve(L, (X.reshape(-1, sh[-1]) - mean).T).T.reshape(sh)


def _chains(label, problem, center, cov, ref_mean, ref_cov, seeds, init, **options):
    """One chain per seed; E[z²] against (ref_mean, ref_cov) and σ ratio against √diag(ref_cov)."""
    rows = []
    for seed in seeds:
        s = sample_posterior(problem, center=center, covariance=cov, seed=seed, progress=False,
                             init_scale=init, **options)
        m2, se = mean_z2(whitened(s.chain, ref_mean, ref_cov))
        r = {"seed": seed, "mean_z2": m2, "mean_z2_se": se,
             "sigma_ratio_mean": float(np.mean(s.std() / np.sqrt(np.diag(ref_cov)))),
             "steps": s.n_steps, "burn_in": s.burn_in, "tau_max": float(s.tau.max()),
             "min_ess": float(s.ess.min()), "wall_s": s.wall_time_s, "ess_per_s": float(s.ess.min() / s.wall_time_s)}
        rows.append(r)
        print(f"{label:<7} init {init:.1f} seed {seed}: E[z²] {m2:.4f} ± {se:.4f}  mean σ ratio "
              f"{r['sigma_ratio_mean']:.4f}  {r['steps']} steps (burn {r['burn_in']}, τ {r['tau_max']:.1f}, "
              f"min ESS {r['min_ess']:.0f}, {r['ess_per_s']:.0f} ESS/s)", flush=True)
    return rows


def run(n_poses, seeds, init_scales, **options):
    sim = simulated_problem("puma560", n_poses=n_poses, seed=2, sigma_p=5e-5, sigma_r=5e-4)
    lin, lm_lin, mu, C = linear_gaussian(sim.problem)
    lm = calibrate_lsq(sim.problem)
    out = {"linear": {}, "puma": {}}
    for init in init_scales:
        # linear: against the exact posterior; PUMA: against LM's Laplace approximation
        out["linear"][init] = _chains("linear", lin, lm_lin.estimate, lm_lin.covariance, mu, C, seeds, init,
                                      noise_scale=False, **options)
        out["puma"][init] = _chains("PUMA", sim.problem, lm.estimate, lm.covariance, lm.estimate, lm.covariance,
                                    seeds, init, **options)
    for kind in ("linear", "puma"):
        for init, rows in out[kind].items():
            v = np.array([r["mean_z2"] for r in rows])
            sr = np.array([r["sigma_ratio_mean"] for r in rows])
            print(f"{kind:<7} init {init:.1f}: over {len(rows)} seeds E[z²] {v.mean():.4f} "
                  f"± {v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else np.nan:.4f} (seed scatter), "
                  f"mean σ ratio {sr.mean():.4f}")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="20 poses, 2 seeds")
    ap.add_argument("--poses", type=int, default=50)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--init-scale", type=float, action="append", help="default: 0.5 and 1")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    n, seeds = (20, range(2)) if a.quick else (a.poses, range(a.seeds))
    res = run(n, list(seeds), a.init_scale or [0.5, 1.0])
    if a.json:
        write_json(a.json, res)


if __name__ == "__main__":
    main()
