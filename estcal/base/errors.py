"""The exceptions and warnings of estcal, one hierarchy for every layer (docs/architecture.md).

* :class:`EstcalError` — the root: every problem estcal reports on purpose.
* :class:`InputError` — bad input (a file, an option, a parameter name): the user can mend it;
  the command line exits with code 2. ``DatasetError``, ``RobotFileError``, ``ParameterError``,
  ``UnidentifiableError`` … derive from it.
* :class:`NumericalRefusal` — well-formed input that the numbers cannot answer honestly
  (too few poses, degenerate data, an ill-conditioned fit): exit code 3
  (docs/reliability.md, "Numerical refusals").
* :class:`MissingExtraError` — an optional dependency is not installed; the message names the
  ``pip install "estcal[EXTRA]"`` that mends it.
* :class:`EstcalWarning` — what estcal warns about (``warnings.warn(msg, EstcalWarning)``);
  the command line prints it as a ``warning: …`` line on stderr.

``InputError`` and ``NumericalRefusal`` are also ``ValueError`` (and ``MissingExtraError`` an
``ImportError``), so that code written against the built-in types keeps catching them.
"""
from __future__ import annotations

__all__ = ["EstcalError", "InputError", "NumericalRefusal", "MissingExtraError", "EstcalWarning", "RobotFileError",
           "OPTIONAL_MODULES", "require", "missing_extra"]


class EstcalError(Exception):
    """A problem that estcal reports on purpose, with a message meant for the user."""


class InputError(EstcalError, ValueError):
    """Bad input: the message names the file, line, option or parameter, and what to do."""


class RobotFileError(InputError):
    """A problem in a robot file or URDF; the message starts with the file name and the key/joint.

    Raised by the robot-file loader (:mod:`estcal.io.robotfile`) and the URDF parser
    (:mod:`estcal.kinematics.urdf`), hence defined here, below both."""


class NumericalRefusal(EstcalError, ValueError):
    """The data or the fit cannot support an honest estimate (the command line's exit code 3)."""


class MissingExtraError(InputError, ImportError):
    """An optional dependency is missing; ``extra`` names the pip extra that installs it."""

    def __init__(self, what: str, extra: str, module: str | None = None):
        self.extra = extra
        super().__init__(f"{what} needs the optional dependency {module or extra!r}: "
                         f"pip install \"estcal[{extra}]\"")
        self.name = module or extra


class EstcalWarning(UserWarning):
    """A warning of estcal (printed by the command line as ``warning: …`` on stderr)."""


#: optional modules → the pip extra of pyproject.toml that installs them (tested against pyproject.toml)
OPTIONAL_MODULES = {"h5py": "mcmc", "arviz": "mcmc", "corner": "mcmc", "dask": "dask", "distributed": "dask"}


def require(module: str, what: str):
    """``import module``, or :class:`MissingExtraError` naming ``what`` needs it and the extra that
    installs it (:data:`OPTIONAL_MODULES`) — never an internal error."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(what, OPTIONAL_MODULES[module.split(".")[0]], module) from None


def missing_extra(exc: BaseException) -> "MissingExtraError | None":
    """The :class:`MissingExtraError` for an ``ImportError`` of an optional module that nothing caught
    where it was imported (the command line's last safety net), else None."""
    name = getattr(exc, "name", None) or ""
    extra = OPTIONAL_MODULES.get(name.split(".")[0])
    if not isinstance(exc, ImportError) or isinstance(exc, MissingExtraError) or extra is None:
        return None
    return MissingExtraError("this command", extra, name)
