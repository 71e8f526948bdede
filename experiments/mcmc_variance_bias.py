"""Is the emcee posterior σ of :func:`estcal.estimate.mcmc.sample_posterior` biased? (docs/mcmc-variance.md)

1. **Linear-Gaussian target with a known posterior.** The PUMA 560 problem (``--poses`` full
   poses, CMM noise 0.05 mm / 0.5 mrad) linearised at the LM optimum, e(θ) = e₀ − H(θ − θ̂),
   is sampled through the same code path (LogPosterior, moves, stopping rule); its posterior is
   exactly N(μ, C), C = (HᵀWH + diag(s⁻²))⁻¹ (s = prior std). Reported per seed: mean over
   the 30 whitened coordinates z = C^{-½}(θ − μ) of var(z) (exactly 1), with its Monte-Carlo
   standard error from batch means over the steps (each coordinate; combined over coordinates).
2. **Nonlinear PUMA case against LM:** σ_MCMC/σ_LM (Laplace) per parameter, mean over the
   parameters, and mean whitened variance against the LM covariance.

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
from estcal.io.jsonio import write_json  # noqa: E402


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


def batch_means_se_of_var(Z, n_batches=20):
    """Standard error of var(z) per coordinate from batch means over steps: Z (steps, walkers, p)."""
    n = Z.shape[0] // n_batches * n_batches
    z2 = (Z[:n] ** 2).mean(1)  # (steps, p): mean over walkers of z² (mean of z is ≈ 0)
    b = z2.reshape(n_batches, -1, Z.shape[2]).mean(1)
    return b.std(0, ddof=1) / np.sqrt(n_batches)


def whitened(X, mean, C):
    L = np.linalg.cholesky(C)
    sh = X.shape
    return np.linalg.solve(L, (X.reshape(-1, sh[-1]) - mean).T).T.reshape(sh)


def run(n_poses, seeds, init_scales, **options):
    sim = simulated_problem("puma560", n_poses=n_poses, seed=2, sigma_p=5e-5, sigma_r=5e-4)
    lin, lm_lin, mu, C = linear_gaussian(sim.problem)
    lm = calibrate_lsq(sim.problem)
    out = {"linear": {}, "puma": {}}
    for init in init_scales:
        rows = []
        for seed in seeds:
            s = sample_posterior(lin, center=lm_lin.estimate, covariance=lm_lin.covariance, seed=seed,
                                 noise_scale=False, progress=False, init_scale=init, **options)
            Z = whitened(s.chain, mu, C)
            v = Z.reshape(-1, Z.shape[-1]).var(0, ddof=1)
            se = batch_means_se_of_var(Z)
            rows.append({"seed": seed, "var_mean": float(v.mean()),
                         "var_mean_se": float(np.sqrt(np.sum(se ** 2)) / v.size),
                         "sigma_ratio_mean": float(np.mean(s.std() / np.sqrt(np.diag(C)))),
                         "steps": s.n_steps, "burn_in": s.burn_in, "tau_max": float(s.tau.max()),
                         "min_ess": float(s.ess.min()), "wall_s": s.wall_time_s,
                         "ess_per_s": float(s.ess.min() / s.wall_time_s)})
            r = rows[-1]
            print(f"linear  init {init:.1f} seed {seed}: mean var(z) {r['var_mean']:.4f} ± {r['var_mean_se']:.4f}  "
                  f"mean σ/σ_exact {r['sigma_ratio_mean']:.4f}  {r['steps']} steps (burn {r['burn_in']}, "
                  f"τ {r['tau_max']:.1f}, min ESS {r['min_ess']:.0f}, {r['ess_per_s']:.0f} ESS/s)", flush=True)
        out["linear"][init] = rows
        rows = []
        for seed in seeds:
            s = sample_posterior(sim.problem, center=lm.estimate, covariance=lm.covariance, seed=seed,
                                 progress=False, init_scale=init, **options)
            Z = whitened(s.chain, lm.estimate, lm.covariance)
            v = Z.reshape(-1, Z.shape[-1]).var(0, ddof=1)
            se = batch_means_se_of_var(Z)
            rows.append({"seed": seed, "sigma_ratio_mean": float(np.mean(s.std() / lm.std)),
                         "var_mean_vs_laplace": float(v.mean()),
                         "var_mean_se": float(np.sqrt(np.sum(se ** 2)) / v.size),
                         "steps": s.n_steps, "min_ess": float(s.ess.min()), "wall_s": s.wall_time_s,
                         "ess_per_s": float(s.ess.min() / s.wall_time_s)})
            r = rows[-1]
            print(f"PUMA    init {init:.1f} seed {seed}: mean σ_MCMC/σ_LM {r['sigma_ratio_mean']:.4f}  "
                  f"mean var(z) vs Laplace {r['var_mean_vs_laplace']:.4f} ± {r['var_mean_se']:.4f}  "
                  f"{r['steps']} steps, min ESS {r['min_ess']:.0f}, {r['ess_per_s']:.0f} ESS/s", flush=True)
        out["puma"][init] = rows
    for kind in ("linear", "puma"):
        for init, rows in out[kind].items():
            key = "var_mean" if kind == "linear" else "var_mean_vs_laplace"
            v = np.array([r[key] for r in rows])
            sr = np.array([r["sigma_ratio_mean"] for r in rows])
            print(f"{kind:<7} init {init:.1f}: over {len(rows)} seeds mean var(z) {v.mean():.4f} "
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
