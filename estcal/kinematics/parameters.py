"""The named parameter vector shared by every model, estimator and effect.

Every calibratable quantity has a stable name and a place in one flat vector:

=====================  =====================================================
name                   meaning (SI)
=====================  =====================================================
``alpha_j`` ``d_j``    Khalil–Kleinfinger frame j (``beta_j``: Hayati angle)
``theta_j`` ``r_j``
``a_j`` ``d_j`` ...    standard DH (``theta, d, a, alpha``)
``tx_J`` .. ``rz_J``   6-D placement error of URDF joint ``J`` (FIGAROH
                       "full_params"): Trans(x,y,z) then Rx, Ry, Rz
``offset_j``           joint offset, ``q = gain * reading + offset``
``gain_j``             joint transmission gain (GECARO K_j)
``base_tx`` .. ``rz``  world -> frame 0: translation + URDF rpy
``tool_tx`` .. ``rz``  frame n -> tool: translation + URDF rpy
``markerk_x`` ..       point k in the tool frame
effect parameters      named by the effect (e.g. ``compliance_2``)
=====================  =====================================================

``j`` is the frame index of Khalil/DH chains (actuated joints 1..n, constant
frames before the first joint 0, after the last joint n+1, ...) and the joint
name for URDF chains. Each parameter also carries a *kind* (``geometric``,
``offset``, ``gain``, ``base``, ``tool``, ``marker``, ``effect``), the label of
its frame, and whether it is free (estimated) or fixed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from estcal.base.errors import InputError
__all__ = ["ParameterVector", "ParameterError", "summarize_names", "unknown_name_message"]

KINDS = ("geometric", "offset", "gain", "base", "tool", "marker", "effect", "other")


class ParameterError(InputError, KeyError):
    """Unknown or inconsistent parameter name; the message lists the valid names."""

    def __str__(self) -> str:  # KeyError quotes its message; we want plain text
        return str(self.args[0]) if self.args else ""


def summarize_names(names: Sequence[str]) -> str:
    """A one-line summary of parameter names for error messages, every name recoverable.

    Two foldings are tried and the shorter is kept: by the last ``_`` (numbered Khalil/DH
    names as a range, ``theta_1…6``; others by suffix, ``base_tx/ty/tz``) and by the first
    ``_`` with equal suffix lists merged (URDF names: ``tx/ty/offset_{arm_1_joint, arm_2_joint}``).
    """
    last: dict[str, list[str]] = {}
    for n in names:
        head, sep, tail = n.rpartition("_")
        last.setdefault(head + sep if sep else n, []).append(tail if sep else "")
    parts = []
    for key, tails in last.items():
        if tails == [""]:
            parts.append(key)
        elif len(tails) > 2 and all(t.isdigit() for t in tails) and \
                [int(t) for t in tails] == list(range(int(tails[0]), int(tails[0]) + len(tails))):
            parts.append(f"{key}{tails[0]}…{tails[-1]}")
        else:
            parts.append(key + "/".join(tails))
    by_last = ", ".join(parts)

    first: dict[str, list[str]] = {}
    for n in names:
        head, sep, tail = n.partition("_")
        first.setdefault(head, []).append(tail if sep else "")
    merged: dict[tuple, list[str]] = {}
    for key, tails in first.items():
        merged.setdefault(tuple(tails), []).append(key)
    parts = []
    for tails, keys in merged.items():
        if tails == ("",):
            parts += keys
        else:
            parts.append("/".join(keys) + "_" + (tails[0] if len(tails) == 1 else "{" + ", ".join(tails) + "}"))
    by_first = ", ".join(parts)
    return min(by_last, by_first, key=len)


def unknown_name_message(name: str, names: Sequence[str]) -> str:
    """``unknown parameter 'x'. Did you mean …? This model has P parameters: …`` (one line)."""
    import difflib

    close = difflib.get_close_matches(name, list(names), n=5, cutoff=0.6)
    hint = f" Did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    return (f"unknown parameter {name!r}.{hint} This model has {len(names)} parameters: "
            f"{summarize_names(names)}")


@dataclass
class ParameterVector:
    """Ordered, named parameters with nominal values and a free/fixed mask.

    Parameters
    ----------
    names : sequence of str
        Unique stable names.
    values : array_like, shape (P,)
        Current values (SI units).
    free : array_like of bool, shape (P,), optional
        Which parameters an estimator may change. Default: all free.
    kinds : sequence of str, optional
        One of ``geometric, offset, gain, base, tool, marker, effect, other``.
    frames : sequence of str, optional
        Label of the frame/joint the parameter belongs to (for priorities/reports).

    Examples
    --------
    >>> pv = ParameterVector(["a", "b"], [1.0, 2.0])
    >>> pv.fix(["a"]).free_names
    ['b']
    """

    names: list[str]
    values: np.ndarray
    free: np.ndarray | None = None
    kinds: list[str] | None = None
    frames: list[str] | None = None
    _index: dict = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.names = list(self.names)
        self.values = np.array(self.values, dtype=float).reshape(-1)
        P = len(self.names)
        if self.values.shape != (P,):
            raise ValueError(f"{P} names but {self.values.size} values")
        self.free = np.ones(P, bool) if self.free is None else np.array(self.free, bool).reshape(-1)
        self.kinds = ["other"] * P if self.kinds is None else list(self.kinds)
        self.frames = [""] * P if self.frames is None else list(self.frames)
        if len(set(self.names)) != P:
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise ValueError(f"duplicate parameter names: {dup}")
        for k in self.kinds:
            if k not in KINDS:
                raise ValueError(f"unknown parameter kind {k!r}; expected one of {KINDS}")
        self._index = {n: i for i, n in enumerate(self.names)}

    # ------------------------------------------------------------------ lookup
    def __len__(self) -> int:
        return len(self.names)

    def __contains__(self, name: str) -> bool:
        return name in self._index

    def index(self, name: str) -> int:
        """Position of ``name`` in the flat vector (clear error if unknown)."""
        try:
            return self._index[name]
        except KeyError:
            raise ParameterError(unknown_name_message(name, self.names)) from None

    def indices(self, names: Iterable[str]) -> np.ndarray:
        return np.array([self.index(n) for n in names], dtype=int)

    def __getitem__(self, name: str) -> float:
        return float(self.values[self.index(name)])

    def __setitem__(self, name: str, value: float) -> None:
        self.values[self.index(name)] = float(value)

    def select(self, pattern: str) -> list[str]:
        """Names matching a shell-style pattern (``fnmatch``), e.g. ``"offset_*"``."""
        import fnmatch

        return [n for n in self.names if fnmatch.fnmatchcase(n, pattern)]

    def names_of_kind(self, *kinds: str) -> list[str]:
        return [n for n, k in zip(self.names, self.kinds) if k in kinds]

    # ------------------------------------------------------------ free/fixed
    @property
    def free_names(self) -> list[str]:
        return [n for n, f in zip(self.names, self.free) if f]

    @property
    def free_indices(self) -> np.ndarray:
        return np.flatnonzero(self.free)

    def copy(self) -> "ParameterVector":
        return ParameterVector(list(self.names), self.values.copy(), self.free.copy(),
                               list(self.kinds), list(self.frames))

    def with_free(self, names: Iterable[str]) -> "ParameterVector":
        """Copy in which exactly ``names`` (patterns allowed) are free."""
        out = self.copy()
        out.free[:] = False
        for n in names:
            matched = self.select(n) if any(ch in n for ch in "*?[") else [n]
            if not matched:
                raise ParameterError(f"pattern {n!r} matches no parameter")
            out.free[self.indices(matched)] = True
        return out

    def fix(self, names: Iterable[str]) -> "ParameterVector":
        """Copy with ``names`` fixed."""
        out = self.copy()
        for n in names:
            matched = self.select(n) if any(ch in n for ch in "*?[") else [n]
            out.free[self.indices(matched)] = False
        return out

    # ------------------------------------------------------------ flat maps
    def to_flat(self) -> np.ndarray:
        """Free values as a flat vector (what an estimator iterates on)."""
        return self.values[self.free].copy()

    def from_flat(self, x: Sequence[float]) -> np.ndarray:
        """Full value vector with the free entries replaced by ``x``."""
        x = np.asarray(x, dtype=float)
        nfree = int(self.free.sum())
        if x.shape[-1] != nfree:
            raise ValueError(f"expected {nfree} free values, got {x.shape[-1]}")
        full = np.broadcast_to(self.values, x.shape[:-1] + self.values.shape).copy()
        full[..., self.free] = x
        return full

    def with_values(self, values: Sequence[float]) -> "ParameterVector":
        out = self.copy()
        out.values = np.array(values, dtype=float).reshape(-1)
        if out.values.shape != self.values.shape:
            raise ValueError("value vector has the wrong length")
        return out

    def extend(self, names: Sequence[str], values: Sequence[float], kind: str = "effect",
               frames: Sequence[str] | None = None, free: bool = True) -> "ParameterVector":
        """Copy with new parameters appended (used by non-geometric effects)."""
        n = len(names)
        return ParameterVector(
            self.names + list(names), np.concatenate([self.values, np.asarray(values, float)]),
            np.concatenate([self.free, np.full(n, free)]), self.kinds + [kind] * n,
            self.frames + (list(frames) if frames is not None else [""] * n),
        )

    # ------------------------------------------------------------ reporting
    def to_dict(self) -> dict:
        return {n: {"value": float(v), "free": bool(f), "kind": k, "frame": fr}
                for n, v, f, k, fr in zip(self.names, self.values, self.free, self.kinds, self.frames)}

    def __repr__(self) -> str:
        return f"ParameterVector({len(self)} parameters, {int(self.free.sum())} free)"

    def table(self) -> str:
        rows = [f"{'name':<22}{'value':>14}  {'kind':<10}free"]
        rows += [f"{n:<22}{v:>14.6g}  {k:<10}{'yes' if f else 'no'}"
                 for n, v, k, f in zip(self.names, self.values, self.kinds, self.free)]
        return "\n".join(rows)
