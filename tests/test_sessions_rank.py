"""The sessions' free-set check goes through the one identifiable-set entry (estcal.identify.select):
a dependent or ineffective parameter is refused by name, a well-posed set passes."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.sessions.fit import _check_rank


def _blocks(rng, dependent=False, dead=False):
    A = [rng.normal(size=(30, 4)) for _ in range(3)]
    for a in A:
        if dependent:
            a[:, 3] = 2.0 * a[:, 0] - a[:, 1]
        if dead:
            a[:, 2] = 0.0
    c = np.sqrt(sum(np.einsum("ij,ij->j", a, a) for a in A))
    return A, np.where(c > 0, c, 1.0)


def test_check_rank_names_dependent_and_dead_parameters():
    rng = np.random.default_rng(3)
    names = ["a", "b", "c", "d"]
    _check_rank(*_blocks(rng), names)  # four independent columns: accepted
    with pytest.raises(ValueError, match=r"\['d'\] have no effect or depend on the others"):
        _check_rank(*_blocks(rng, dependent=True), names)
    with pytest.raises(ValueError, match=r"\['c'\] have no effect"):
        _check_rank(*_blocks(rng, dead=True), names)
    A, c = _blocks(rng)
    for a in A:
        a[:, 3] = a[:, 0] + 1e-7 * a[:, 3]  # independent, but not determined by noisy data
    with pytest.raises(ValueError, match="condition number"):
        _check_rank(A, c, names)
