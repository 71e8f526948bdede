"""Layer 9 of estcal (docs/architecture.md): one module per job, under both faces.

The command line (:mod:`estcal.cli`) and the Python API (:mod:`estcal.api`) call the same
functions here. A workflow loads its inputs (robot specs, files or objects), checks them, runs
the analyses of the lower layers and returns a result object; it raises the typed errors of
:mod:`estcal.base.errors` (``InputError`` and its subclasses, ``NumericalRefusal``,
``MissingExtraError``) and warns with ``warnings.warn(msg, EstcalWarning)``. It never prints
and never exits: the faces decide how to show results, errors and warnings.

=====================  ==========================================================
module                 job
=====================  ==========================================================
``inputs``             loading and checking what every job reads (shared)
``calibrate``          batch calibration (``estcal calibrate``, ``estcal.calibrate``)
``left_out``           the rows a calibration left out, and the fit with them
``diagnose``           what the geometric model gets wrong (``estcal diagnose``)
``sessions``           several sessions with a repeatability model
``design``             measurement plans and the next pose
``fleet``              a folder of robots, serially or on Dask
``simulate``           simulated datasets with their ground truth
``compensate``         corrected joint commands from a calibrated model
``export``             a model as URDF
``identifiable``       identifiable (base) parameters
``fk``                 forward kinematics of a dataset
``demo``               simulate → calibrate → validate, end to end
``gough``              Gough–Stewart platforms: calibration, identifiability, simulation
``online``             row-by-row calibration (the online calibrator)
``robots``             the robots ``--robot`` accepts by name
=====================  ==========================================================

Import the modules themselves (``from estcal.workflows.calibrate import calibrate``): this
face imports nothing, so that the command line's start-up pays for no job it does not run.
"""
