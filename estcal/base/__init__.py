"""Layer 0 of estcal (docs/architecture.md): what every other layer may use and which uses
nothing of estcal — the exception/warning hierarchy, display units, progress bars, atomic
files and locks, JSON, the text-input layer and the version.

Import the modules themselves (``from estcal.base.errors import InputError``): this face
imports nothing, so that a light module pays for no heavy one.
"""
