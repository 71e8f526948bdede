"""Measurement noise per kind and axis by REML (estcal.discrepancy.noise)."""
import numpy as np
import pytest

from estcal.discrepancy.noise import measurement_noise, reml_variance_components


def test_reml_is_unbiased_where_the_residual_variance_is_not():
    # linear model with many parameters: residual variance is biased by (M − p)/M, REML is not
    rng = np.random.default_rng(0)
    M, p = 120, 40
    A = rng.standard_normal((M, p))
    cls = np.arange(M) % 2
    sig = np.where(cls == 0, 1.0, 3.0)
    est, naive = [], []
    for _ in range(60):
        y = A @ rng.standard_normal(p) + sig * rng.standard_normal(M)
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        c = reml_variance_components(A, r, cls, ["a", "b"])
        est.append([c["a"]["std"] ** 2, c["b"]["std"] ** 2])
        naive.append([np.mean(r[cls == 0] ** 2), np.mean(r[cls == 1] ** 2)])
    est, naive = np.mean(est, 0), np.mean(naive, 0)
    assert est == pytest.approx([1.0, 9.0], rel=0.1)
    assert naive[1] < 0.8 * 9.0  # the plain residual variance is biased low by ~p/M


def test_per_axis_noise_of_a_camera_like_instrument_is_recovered():
    from estcal.discrepancy.geometric import fit_geometric
    from estcal.kinematics.robots import puma560
    from estcal.methods import NoiseModel
    from estcal.simulate import simulate

    sim = simulate(puma560(), n_poses=150, measure="position", errors="random", seed=3)
    d = sim.dataset.subset(slice(None))
    sd = np.array([5e-5, 5e-5, 2e-4])  # depth (z) four times the lateral noise
    d.points = sim.true_points[:, :1] + sd * np.random.default_rng(4).standard_normal(d.points.shape)
    pb, res, free, _ = fit_geometric(sim.nominal_robot, d, NoiseModel(position=1e-4), level="full")
    out = measurement_noise(pb, res.theta, free)
    for ax, s in zip("xyz", sd):
        c = out[f"position_{ax}_mm"]
        assert abs(c["std"] - s * 1e3) < 3 * c["std_se"] + 0.1 * s * 1e3, (ax, c)
    assert "REML" in out["estimated"]
