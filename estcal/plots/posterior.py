"""Posterior corner plot of an MCMC calibration (``corner`` package)."""
from __future__ import annotations

import numpy as np

from . import new_figure

__all__ = ["corner_figure"]


def corner_figure(samples, names, truths=None, max_params: int = 8, quantiles=(0.025, 0.5, 0.975)):
    """Corner plot of the first ``max_params`` columns of ``samples`` (n_draws, p), in
    display units, with the 2.5 / 50 / 97.5 % quantiles marked on the marginals.

    Requires the optional ``corner`` package (``pip install estcal[mcmc]``):
    :class:`~estcal.base.errors.MissingExtraError` (an ImportError) naming it otherwise.
    """
    from estcal.base.errors import require

    corner = require("corner", "the posterior corner plot")

    X = np.asarray(samples, float)
    k = min(max_params, X.shape[1])
    dim = 1.6 * k + 1.0
    fig = new_figure(dim, dim, layout=None)
    corner.corner(X[:, :k], labels=list(names[:k]), truths=None if truths is None else np.asarray(truths)[:k],
                  quantiles=list(quantiles), fig=fig, label_kwargs={"fontsize": 8})
    return fig
