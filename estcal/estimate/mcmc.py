"""Posterior sampling of the calibration parameters with emcee.

Model
-----
Free parameters θ (the identifiable set: check it first, an unidentifiable
direction gives an improper, prior-dominated posterior) and, optionally, a
noise scale λ multiplying every σ::

    log p(θ, λ | data) = −½ Σ_i (e_i(θ) / (λ σ_i))² − M log λ        (Gaussian likelihood)
                         −½ Σ_j ((θ_j − θ_j⁰) / s_j)²                (prior, documented below)
                         + const     (λ: flat prior on log λ, i.e. Jeffreys' 1/λ)

* **prior on θ**: independent Gaussians centred on the nominal (initial)
  values with std ``s_j`` — by default 0.1 (m, rad, or dimensionless for gains;
  :func:`~estcal.estimate._common.default_prior_std`), wide enough to be
  negligible against mm-level data yet proper;
* **noise scale**: sampled when the noise is not known (``NoiseModel.known =
  False``) or when asked (``noise_scale=True``); fixed at 1 otherwise.

Sampler
-------
emcee's ensemble sampler with ``vectorize=True``: the log-posterior receives
all walkers at once and evaluates their residuals in one vectorised forward
kinematics (:meth:`estcal.methods.problem.Problem.evaluate_many`, effects included). Walkers start as
draws from the Laplace approximation around the least-squares optimum (see
"Start" below), and the sampler works in the coordinates that whiten it
(θ = θ̂ + L z, L Lᵀ = Σ_LS). Default moves (``moves="laplace"``): 70 %
independence Metropolis–Hastings proposals from the Laplace approximation
inflated by ``proposal_scale`` (exact MH acceptance, so the target is the
true posterior, not its approximation) and 30 % differential evolution; for
the near-Gaussian posteriors of calibration this gives τ of a few steps where
emcee's stretch move needs ~300 and DE ~100 in 30 dimensions (measured in
``benchmarks/bench_probabilistic.py``). ``moves="de"`` (DE-MC, without emcee's
snooker move, which samples a wrong distribution) / ``"stretch"`` select the
classic ensemble moves.

Chain length is chosen by the diagnostics: the chain grows by ``check_every``
steps until (a) it is longer than 50 integrated autocorrelation times τ
(emcee's reliability rule for τ itself) and (b) the effective sample size
ESS = n_walkers · (n_steps − burn-in)/τ reaches ``target_ess`` for every
parameter, or ``max_steps`` is hit (then ``converged = False``). Burn-in is 3 max τ.

Start
-----
The walkers are independent draws from the Laplace approximation N(θ̂, Σ_LS)
itself (``init_scale = 1``), not emcee's customary small ball: for the
near-Gaussian calibration posterior that is already (almost) the stationary
distribution, so the 3 τ burn-in only has to absorb the small non-Gaussian part.
A shrunken start (the former ``0.5``) is *not* removed by a 3 τ burn-in: the
independence proposal leaves an over-concentrated walker slowly (a state where
posterior/proposal is large is rarely left), a transient of ~15 τ, while τ
measures the stationary mixing only. With the default stopping rule (~600 steps)
that transient made every posterior σ ≈ 1.5–2 % too small (variance ≈ 3 % low,
measured against the exact covariance of a linear-Gaussian problem in
``experiments/mcmc_variance_bias.py``; test
``tests/test_mcmc_variance.py``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from estcal.base.lock import LockedError, RunLock
from estcal.plots.posterior import corner_figure

from ._common import evaluate_many, finish_result, noise_known, prior_std_vector, resolve_free
from .chainfile import ChainFileError, check_chain_path

__all__ = ["calibrate_mcmc", "sample_posterior", "PosteriorSamples", "LogPosterior"]


class LogPosterior:
    """Vectorised log-posterior over whitened coordinates z (θ = x̂ + L z) and optionally log λ."""

    def __init__(self, problem, fidx, theta, prior_mean, prior_std, center, L, noise_scale: bool):
        self.problem = problem
        self.fidx = fidx
        self.theta = theta
        self.mu = prior_mean
        self.s = prior_std
        self.center = center
        self.L = L
        self.noise_scale = noise_scale
        self.sigma = problem.evaluate(theta, jacobian=False).sigma
        self.M = self.sigma.size
        self.n_evals = 0

    @property
    def ndim(self) -> int:
        return self.fidx.size + int(self.noise_scale)

    def to_theta(self, Z):
        Z = np.atleast_2d(Z)
        return self.center + Z[:, :self.fidx.size] @ self.L.T

    def __call__(self, Z):
        Z = np.atleast_2d(Z)
        X = self.to_theta(Z)
        TH = np.broadcast_to(self.theta, (X.shape[0], self.theta.size)).copy()
        TH[:, self.fidx] = X
        E = evaluate_many(self.problem, TH) / self.sigma
        self.n_evals += X.shape[0]
        chi2 = np.einsum("wm,wm->w", E, E)
        lp = -0.5 * np.sum(((X - self.mu) / self.s) ** 2, axis=1)
        if self.noise_scale:
            loglam = Z[:, -1]
            ll = -0.5 * chi2 * np.exp(-2 * loglam) - self.M * loglam
            ll = np.where(np.abs(loglam) < 5, ll, -np.inf)  # flat prior on log λ in (−5, 5)
        else:
            ll = -0.5 * chi2
        out = ll + lp
        return np.where(np.isfinite(out), out, -np.inf)


@dataclass
class PosteriorSamples:
    """Posterior draws after burn-in: ``chain`` (n_draws, n_walkers, p) in parameter units."""

    names: list
    chain: np.ndarray
    log_prob: np.ndarray
    tau: np.ndarray
    acceptance_fraction: float
    n_steps: int
    burn_in: int
    n_walkers: int
    ess: np.ndarray
    converged: bool
    wall_time_s: float
    n_evaluations: int
    noise_scale: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    @property
    def flat(self) -> np.ndarray:
        return self.chain.reshape(-1, self.chain.shape[-1])

    def mean(self):
        return self.flat.mean(0)

    def std(self):
        return self.flat.std(0, ddof=1)

    def interval(self, level: float = 0.95):
        a = (1 - level) / 2
        return np.quantile(self.flat, [a, 1 - a], axis=0).T

    def to_inference_data(self):
        """ArviZ InferenceData (chains = walkers); :class:`~estcal.base.errors.MissingExtraError` (an
        ImportError) naming the ``mcmc`` extra without arviz."""
        from estcal.base.errors import require

        az = require("arviz", "MCMCResult.to_inference_data")

        post = {n: self.chain[:, :, i].T for i, n in enumerate(self.names)}
        if self.noise_scale is not None:
            post["noise_scale"] = self.noise_scale.T
        return az.from_dict(posterior=post, sample_stats={"lp": self.log_prob.T})

    def corner_figure(self, params=None, truths=None):
        """Corner plot (:func:`estcal.plots.posterior.corner_figure`, a matplotlib Figure) of ``params``
        (default: up to the first 8); save it with :func:`estcal.report.figures.save_figure`."""
        idx = list(range(min(8, len(self.names)))) if params is None else [self.names.index(p) for p in params]
        return corner_figure(self.flat[:, idx], [self.names[i] for i in idx],
                             truths=None if truths is None else np.asarray(truths)[idx])


def _laplace_move(mean, sd):
    """Independence Metropolis–Hastings proposal from the (inflated) Laplace approximation.

    In the whitened coordinates the Laplace approximation is N(0, I); proposing
    x' ~ N(mean, diag(sd²)) independently of the current x, the MH correction is
    log q(x) − log q(x'). Exact MCMC whatever the posterior's shape; efficient
    (τ of a few steps) when the posterior is close to Gaussian, as calibration
    posteriors with mm-level noise are.
    """
    import emcee

    mean = np.asarray(mean, float)
    sd = np.asarray(sd, float)

    def proposal(coords, random):
        new = mean + sd * random.randn(*coords.shape)
        logq = lambda x: -0.5 * np.sum(((x - mean) / sd) ** 2, axis=1)  # noqa: E731
        return new, logq(coords) - logq(new)

    return emcee.moves.MHMove(proposal)


def _moves(kind, mean=None, sd=None):
    import emcee

    if kind == "stretch":
        return None
    if kind == "de":
        # DE-MC (ter Braak 2006) only. emcee 3.1.6's DESnookerMove is not a valid MH move: its
        # step along x − z is scaled by |x − z| (u = δ/√|δ|, not δ/|δ|) and its Jacobian term is
        # ½(d−1) log(|x' − z|/|x − z|) instead of (d−1) log(...) (ter Braak & Vrugt 2008); on an
        # exact Gaussian target in 30 dimensions it gives variances 0.55 of the truth alone and
        # 0.75 at its former 20 % weight (docs/mcmc-variance.md).
        return [(emcee.moves.DEMove(), 1.0)]
    if kind == "laplace":
        return [(_laplace_move(mean, sd), 0.7), (emcee.moves.DEMove(), 0.3)]
    raise ValueError(f"unknown moves {kind!r}; choose 'laplace', 'de' or 'stretch'")


def sample_posterior(problem, free=None, *, prior_std=None, noise_scale: bool | None = None, n_walkers=None,
                     target_ess: float = 1000.0, max_steps: int = 20000, min_steps: int = 200,
                     check_every: int = 100, seed=0, progress: bool | None = None, moves: str = "laplace", theta0=None,
                     center=None, covariance=None, tau_factor: float = 50.0,
                     proposal_scale: float = 1.2, init_scale: float = 1.0, chain=None) -> PosteriorSamples:
    """Run emcee until the ESS of every parameter reaches ``target_ess`` (see module docstring).

    ``center`` / ``covariance`` : Laplace approximation to start from (default: an LM fit).
    ``init_scale`` : walkers start as draws from the Laplace approximation with its covariance
    scaled by ``init_scale²`` (1: the approximation itself, see the module docstring, "Start").
    ``chain`` : HDF5 file holding the chain (:mod:`estcal.estimate.chainfile`); when it holds a
    chain of the same target, sampling continues it (``max_steps`` counts the stored steps too).
    ``progress`` : bar of the steps on stderr (None: only on a terminal, not in CI —
    :func:`estcal.base.progress.progress`; True forces it, False suppresses it).
    A ``chain`` file is locked for the run (:class:`estcal.base.lock.RunLock`): a second run on the
    same file raises :class:`~estcal.estimate.chainfile.ChainFileError` at once.
    """
    kw = dict(prior_std=prior_std, noise_scale=noise_scale, n_walkers=n_walkers, target_ess=target_ess,
              max_steps=max_steps, min_steps=min_steps, check_every=check_every, seed=seed, progress=progress,
              moves=moves, theta0=theta0, center=center, covariance=covariance, tau_factor=tau_factor,
              proposal_scale=proposal_scale, init_scale=init_scale, chain=chain)
    if chain is None:
        return _sample_posterior(problem, free, **kw)


    check_chain_path(chain)  # before the lock file is made beside it
    try:
        lock = RunLock(chain, "--chain").acquire()
    except LockedError as exc:
        raise ChainFileError(str(exc)) from None
    try:
        return _sample_posterior(problem, free, **kw)
    finally:
        lock.release()


def _sample_posterior(problem, free, *, prior_std, noise_scale, n_walkers, target_ess, max_steps, min_steps,
                      check_every, seed, progress, moves, theta0, center, covariance, tau_factor, proposal_scale,
                      init_scale, chain) -> PosteriorSamples:
    import emcee

    t0 = time.perf_counter()
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    if noise_scale is None:
        noise_scale = not noise_known(problem)
    s = prior_std_vector(problem, names, prior_std)
    backend = saved = None
    if chain is not None:
        from .chainfile import fingerprint, open_chain

        d = fidx.size + int(noise_scale)
        nw_ = int(n_walkers or max(2 * d + 2, 64))
        fp = fingerprint(problem, theta, {"prior_std": s.tolist(), "noise_scale": bool(noise_scale),
                                          "moves": moves, "proposal_scale": proposal_scale, "seed": seed})
        backend, saved = open_chain(chain, names=names, fp=fp, n_walkers=nw_, ndim=d)
        if saved is not None:  # the frame the stored coordinates are written in
            center, covariance = saved["center"], saved["covariance"]
    if center is None or covariance is None:
        from .lsq import calibrate_lsq

        ls = calibrate_lsq(problem, theta0=theta)
        center, covariance = ls.estimate, ls.covariance
    center = np.asarray(center, float)
    L = np.linalg.cholesky(np.asarray(covariance, float) + 1e-30 * np.eye(len(center)))
    post = LogPosterior(problem, fidx, theta, theta[fidx].copy(), s, center, L, noise_scale)
    d = post.ndim
    nw = int(n_walkers or max(2 * d + 2, 64))
    rng = np.random.default_rng(seed)
    p0 = float(init_scale) * rng.standard_normal((nw, d))
    if noise_scale:
        r = problem.evaluate(theta_full_of(theta, fidx, center), jacobian=False)  # start log λ at log σ0
        p0[:, -1] = 0.5 * np.log(np.sum((r.e / r.sigma) ** 2) / max(r.e.size - len(fidx), 1)) \
            + 0.01 * rng.standard_normal(nw)
    pmean = np.zeros(d)
    psd = np.full(d, proposal_scale)
    if noise_scale:
        pmean[-1] = p0[:, -1].mean()
        psd[-1] = proposal_scale / np.sqrt(2.0 * max(post.M - len(fidx), 1))
    sampler = emcee.EnsembleSampler(nw, d, post, vectorize=True, moves=_moves(moves, pmean, psd),
                                    backend=backend)
    n = 0
    state = p0
    if saved is not None:  # continue: the backend restored the random state; start from the last step
        n = int(backend.iteration)
        state = None
    else:
        sampler.random_state = np.random.RandomState(int(rng.integers(2 ** 31))).get_state()
        if backend is not None:
            from .chainfile import write_frame

            sampler.reset()  # an empty chain left by a run killed before its first block
            write_frame(chain, names=names, fp=fp, n_walkers=nw, ndim=d, center=center, covariance=covariance)
    from estcal.base.progress import progress as _progress

    converged = False
    tau = np.full(d, np.nan)
    ess = np.zeros(d)
    burn = 0
    with _progress(total=max_steps, desc="mcmc", unit="step", enabled=progress) as bar:
        if n:
            bar.update(n)
        while n < max_steps:
            k = min(check_every, max_steps - n)
            state = sampler.run_mcmc(state, k, progress=False)
            if backend is not None:
                backend.maybe_flush()
            n += k
            bar.update(k)
            tau = np.asarray(sampler.get_autocorr_time(tol=0, quiet=True), float)
            # τ is NaN when a walker has not moved at all yet (zero variance): not converged
            tmax = float(np.max(tau)) if np.isfinite(tau).all() else float(n)
            burn = int(min(np.ceil(3 * tmax), n // 2))
            ess = nw * (n - burn) / tau
            bar.set_postfix(tau=f"{tmax:.0f}", ess=f"{ess.min():.0f}")
            if n >= min_steps and n > tau_factor * tmax and ess.min() >= target_ess:
                converged = True
                break
    if saved is not None and not np.isfinite(tau).any():  # resumed at or past max_steps: diagnose only
        tau = np.asarray(sampler.get_autocorr_time(tol=0, quiet=True), float)
        burn = int(min(np.ceil(3 * float(np.nanmax(tau))), n // 2))
        ess = nw * (n - burn) / tau
        converged = bool(n > tau_factor * np.nanmax(tau) and ess.min() >= target_ess)
    if backend is not None:
        backend.flush()
    zs = sampler.get_chain(discard=burn)
    lp = sampler.get_log_prob(discard=burn)
    X = post.to_theta(zs.reshape(-1, d)).reshape(zs.shape[0], nw, len(fidx))
    lam = np.exp(zs[..., -1]) if noise_scale else None
    return PosteriorSamples(names, X, lp, tau[:len(fidx)], float(np.mean(sampler.acceptance_fraction)), n, burn, nw,
                            ess[:len(fidx)], converged, time.perf_counter() - t0, post.n_evals, lam,
                            {"tau_noise_scale": float(tau[-1]) if noise_scale else None, "moves": moves,
                             "prior_std": s})


def theta_full_of(theta, fidx, x):
    th = np.asarray(theta, float).copy()
    th[fidx] = x
    return th


def calibrate_mcmc(problem, free=None, validation=(), *, level: float = 0.95, **options):
    """Posterior summary as a :class:`CalibrationResult` (same JSON as the other methods).

    ``estimate`` = posterior mean, ``std`` = posterior std, ``covariance`` = sample covariance;
    ``extra``: ``credible_intervals`` ({name: [lo, hi]} at ``level``), ``posterior_median``,
    ``tau``, ``ess``, ``acceptance_fraction``, ``n_steps``, ``n_walkers``, ``burn_in``,
    ``noise_scale`` (mean, std) when sampled; the draws are in ``result.samples`` (the corner plot
    of ``--report DIR``: :func:`estcal.plots.posterior.corner_figure`).
    Options are those of :func:`sample_posterior`.
    """
    t0 = time.perf_counter()
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if options.get("theta0") is None else np.asarray(options["theta0"], float)
    smp = sample_posterior(problem, **options)
    flat = smp.flat
    mean = flat.mean(0)
    cov = np.cov(flat.T)
    ci = smp.interval(level)
    extra = {"credible_level": level,
             "credible_intervals": {n: [float(a), float(b)] for n, (a, b) in zip(names, ci)},
             "posterior_median": np.median(flat, 0), "tau": smp.tau, "ess": smp.ess,
             "min_ess": float(np.min(smp.ess)), "acceptance_fraction": smp.acceptance_fraction,
             "n_steps": smp.n_steps, "n_walkers": smp.n_walkers, "burn_in": smp.burn_in,
             "n_evaluations": smp.n_evaluations, "sampling_time_s": smp.wall_time_s,
             "moves": smp.extra["moves"], "prior_std": smp.extra["prior_std"]}
    if smp.noise_scale is not None:
        extra["noise_scale"] = {"mean": float(smp.noise_scale.mean()), "std": float(smp.noise_scale.std())}
    res = finish_result(problem, "mcmc", names, fidx, mean, cov, theta_full_of(theta, fidx, mean), theta[fidx],
                        n_iterations=smp.n_steps, converged=smp.converged, covariance_source="posterior samples",
                        theta_before=theta, validation=validation, t0=t0, extra=extra)
    res.samples = flat
    return res
