"""One grouping of the rows — posture, session, acquisition time — that every cross-validation takes.

A held-out row must be new in every way the model will meet new data: a posture it was not fitted at
(:mod:`.postures`), a session it did not see (another day: the measuring frame re-set, the robot restarted),
a later time (the robot is calibrated first and used afterwards). Cross-validation under such structure
holds out whole groups, never single rows (Roberts et al. 2017, *Ecography* 40:913, "Cross-validation
strategies for data with temporal, spatial, hierarchical, or phylogenetic structure"):

* ``"posture"`` — folds of whole postures, every session pooled (:func:`.postures.grouped_folds`);
* ``"session"`` — with two or more sessions, each fold holds out the rows of *one session* at one set of
  postures, and trains on the *other* sessions' rows at the other postures: posture- and session-disjoint.
  The held-out session's measuring frame is not known to the fold's model; it is registered on that
  session's rows at postures the fold's model was fitted at (``register`` rows), as a validation file of
  another day is (docs/discrepancy.md);
* ``"time"`` — contiguous blocks of acquisition time within each session (by the ``t`` column, or the row
  order of the file when there is none: rows are assumed to be in acquisition order, and the output says
  so); the block's postures are left out of the training rows too, so a block is new in time *and* posture.

A fold is ``Fold(test, train, register)``: row indices of the held-out rows, the training rows, and the rows
that register a held-out session's frame (empty unless ``"session"``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .postures import DEFAULT_TOL_M, DEFAULT_TOL_RAD, grouped_folds, posture_groups

__all__ = ["Fold", "Groups", "row_groups", "FOLD_KINDS"]

#: the kinds of fold :meth:`Groups.folds` draws
FOLD_KINDS = ("posture", "session", "time")


@dataclass
class Fold:
    """One cross-validation fold: ``test`` (held-out rows), ``train`` (fitting rows), ``register`` (rows of the
    held-out session at postures seen in training, which fix its measuring frame; empty when the held-out
    rows' session is in training)."""

    test: np.ndarray
    train: np.ndarray
    register: np.ndarray = field(default_factory=lambda: np.zeros(0, int))


@dataclass
class Groups:
    """The structure of the rows of a (stacked) dataset.

    posture : (N,) posture labels (:func:`.postures.posture_groups`)
    session : (N,) session labels (one value when one session)
    time : (N,) acquisition time within its session (s), or the row index when ``time_source == "row order"``
    time_source : ``"t column"`` or ``"row order"``
    readings : (N, n) the joint readings (how far a held-out row lies beyond its fold's training ranges)
    """

    posture: np.ndarray
    session: np.ndarray
    time: np.ndarray
    time_source: str
    readings: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.posture)

    @property
    def sessions(self) -> list:
        return list(dict.fromkeys(np.asarray(self.session).tolist()))

    @property
    def n_postures(self) -> int:
        return int(len(np.unique(self.posture)))

    def subset(self, rows) -> "Groups":
        rows = np.asarray(rows)
        return Groups(self.posture[rows], self.session[rows], self.time[rows], self.time_source,
                      None if self.readings is None else self.readings[rows])

    def folds(self, kind: str = "posture", k: int = 5, rng=0) -> list[Fold]:
        """The folds of ``kind`` (module docstring); ``"session"`` with one session is ``"posture"``."""
        if kind not in FOLD_KINDS:
            raise ValueError(f"fold kind must be one of {FOLD_KINDS}, got {kind!r}")
        every = np.arange(self.n)
        if kind == "time":
            return self._time_folds(k)
        pf = grouped_folds(self.posture, k, rng)
        if kind == "posture" or len(self.sessions) < 2:
            return [Fold(t, np.setdiff1d(every, t)) for t in pf]
        out = []
        for t in pf:
            held_postures = np.unique(self.posture[t])
            for s in self.sessions:
                test = t[self.session[t] == s]
                train = np.flatnonzero((self.session != s) & ~np.isin(self.posture, held_postures))
                if not len(test) or not len(train):
                    continue
                reg = np.flatnonzero((self.session == s) & np.isin(self.posture, self.posture[train])
                                     & ~np.isin(self.posture, held_postures))
                out.append(Fold(test, train, reg))
        return out

    def _time_folds(self, k: int) -> list[Fold]:
        """``k`` contiguous blocks of time in every session; fold i holds out block i of every session, and
        the training rows exclude the held-out postures."""
        block = np.zeros(self.n, int)
        for s in self.sessions:
            m = np.flatnonzero(self.session == s)
            order = m[np.argsort(self.time[m], kind="stable")]
            kk = int(min(max(k, 2), len(order)))
            for i, part in enumerate(np.array_split(order, kk)):
                block[part] = i
        out = []
        for i in range(int(block.max()) + 1):
            test = np.flatnonzero(block == i)
            train = np.flatnonzero(~np.isin(self.posture, self.posture[test]))
            if len(test) and len(train):
                out.append(Fold(test, train))
        return out


def row_groups(readings, joint_types=None, session=None, t=None, tol=(DEFAULT_TOL_RAD, DEFAULT_TOL_M)) -> Groups:
    """:class:`Groups` of rows: postures from ``readings`` (N, n), ``session`` labels (default one), ``t``
    (N,) the time column when the data have one (else the row order within each session)."""
    R = np.asarray(readings, float)
    N = R.shape[0]
    sess = np.zeros(N, int) if session is None else np.asarray(session)
    if t is None:
        time = np.zeros(N)
        for s in dict.fromkeys(sess.tolist()):
            m = np.flatnonzero(sess == s)
            time[m] = np.arange(len(m), dtype=float)
        source = "row order"
    else:
        time, source = np.asarray(t, float), "t column"
    return Groups(posture_groups(R, joint_types, *tol), sess, time, source, R)
