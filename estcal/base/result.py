"""The protocol every result of estcal follows (docs/architecture.md, "Results").

A result is plain data that prints nicely and serialises:

* ``to_dict()`` — JSON-ready data (SI units; the unit in every key that is not SI);
* ``to_json(path)`` — that dict written atomically as strict JSON; the inputs the result was
  computed from (``inputs``) are never written over;
* ``save_model(path, provenance=None)`` — the identified robot as a saved model (robot file with
  a ``calibration:`` block), for the results that hold one;
* ``table()`` — the parameter table, a :class:`~estcal.base.tables.Table` (``str()`` gives the
  text; the reports render it as HTML);
* ``repr()`` / ``str()`` — a one-line summary and the table.

:class:`Result` implements ``to_json`` and the printing from ``to_dict``, ``table`` and
``summary``; a result class derives from it (as a ``@dataclass(repr=False)``, so that the
printing is this one) and implements the rest. Implemented by
:class:`~estcal.estimate.result.CalibrationResult` and :class:`~estcal.sessions.fit.SessionFit`.
"""
from __future__ import annotations

from pathlib import Path

from .atomic import refuse_input
from .jsonio import write_json

__all__ = ["Result"]


class Result:
    """Base class of the results (module docstring)."""

    #: files the result was computed from (dataset, validation files, robot file): never written over
    inputs: tuple = ()

    def to_dict(self) -> dict:
        raise NotImplementedError(f"{type(self).__name__}.to_dict")

    def table(self):
        """The parameter table (:class:`~estcal.base.tables.Table`)."""
        raise NotImplementedError(f"{type(self).__name__}.table")

    def save_model(self, path, provenance: dict | None = None) -> Path:
        raise NotImplementedError(f"{type(self).__name__} holds no robot model to save")

    def summary(self) -> str:
        """One line: what the result is."""
        return type(self).__name__

    def to_json(self, path) -> Path:
        """Write :meth:`to_dict` to ``path`` as strict JSON (atomically); an input file is refused."""
        refuse_input(path, self.inputs)
        return write_json(path, self.to_dict())

    def __str__(self) -> str:
        return f"{self.summary()}\n{self.table()}"

    def __repr__(self) -> str:
        return str(self)
