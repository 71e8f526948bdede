"""Units on the command line (docs/conventions.md, "Units on the command line").

One convention for every subcommand:

* files (CSV, YAML, JSON) are SI: m, rad, s, kg;
* printed tables are mm and mrad (joint poses: degrees / mm);
* a length or angle typed as an option is in mm or mrad and the option's name
  says so (``--noise-pos-mm``, ``--noise-rot-mrad``); a joint quantity is in
  mrad for revolute and mm for prismatic joints (``--noise-joint-mrad``); a
  width of *parameters* (prior std, process noise) is in each parameter's
  milli-unit (mm, mrad, 10⁻³ for dimensionless gains: ``--prior-std-mm``);
  a joint pose typed as ``q1,q2,…`` is in degrees / mm, as the plans print it;
* options whose values go verbatim into a named parameter or an estimator
  (``--effect-param NAME=VALUE``, ``--option KEY=VALUE``) are SI like the files.

Options renamed when this convention was introduced stay accepted as hidden
aliases in their old unit: the value is converted and a warning names the new
option (:func:`resolve`).

Every numeric option names its unit in its name or help, or is in
:data:`DIMENSIONLESS` (checked by ``tests/test_cli_units.py`` over every
subcommand's ``--help``).
"""
from __future__ import annotations

import warnings

from estcal.base.errors import EstcalWarning, InputError

__all__ = ["resolve", "DIMENSIONLESS", "UNIT_PATTERN"]


# Numeric options without a physical unit (option name: what it counts or measures).
DIMENSIONLESS = {
    "--n": "number of poses",
    "--n-poses": "number of configurations",
    "--n-candidates": "number of candidate poses",
    "--random-plans": "number of random plans",
    "--restarts": "number of optimiser restarts",
    "--accuracy-map": "number of poses of the accuracy map",
    "--points": "number of measured / simulated points",
    "--seed": "random seed",
    "--folds": "cross-validation folds",
    "--every": "rows between status lines",
    "--show": "number of parameters shown",
    "--model": "Gough model size (42 / 36 parameters)",
    "--alpha": "significance level (probability)",
    "--margin": "fraction of each joint range",
    "--error-gain": "σ of relative joint-gain errors (gain is dimensionless)",
    "--tau-floor": "threshold on unit-norm columns",
    "--n-jobs": "number of worker processes",
    "--workers": "number of worker processes",
    "--chunk": "rows per chunk",
    "--burn-in": "number of rows / samples",
    "--walkers": "number of MCMC walkers",
    "--steps": "number of MCMC steps",
    "--max-iter": "number of iterations",
    "--recalibrate": "number of re-measured poses",
    "--checkpoint-every": "rows between checkpoints",
}

# A unit written in an option's name (suffix) or help: "(mm)", "mrad", "deg", "°C", "kg", "s" …
UNIT_PATTERN = (r"(\bmm\b|\bmrad\b|\bm\b|\brad\b|\bdeg\b|degrees|°|\bs\b|[Ss]econds|\bkg\b|\bSI\b|"
                r"m/s|\bN\b|\bHz\b|1/m|[Mm]illi(metres|radians)|[Mm]etres|[Rr]adians)")


def resolve(value: float, scale: float, old_value, old_option: str, new_option: str, old_unit: str,
            old_scale: float, default: float | None = None) -> float:
    """SI value of an option pair: the current ``value`` (× ``scale`` to SI), or the deprecated
    ``old_value`` (× ``old_scale``) with an :class:`~estcal.base.errors.EstcalWarning` naming the
    new option.

    ``default``: the new option's default; if both options were given, an ``InputError``.
    """
    if old_value is None:
        return value * scale
    if default is not None and value != default:
        raise InputError(f"give {new_option} or the deprecated {old_option}, not both")
    new_value = old_value * old_scale / scale
    warnings.warn(f"{old_option} ({old_unit}) is deprecated; use {new_option} {new_value:g} "
                  f"(docs/conventions.md, 'Units on the command line')", EstcalWarning, stacklevel=2)
    return old_value * old_scale


# the shared declarations moved to estcal.cli.options; these names stay for the modules that import them here
from estcal.cli.options import deprecated_option, noise_pos_option, noise_rot_option  # noqa: E402
