"""Data intake: what a measured file must pass before a fit.

* :mod:`estcal.intake.registration` — closed-form and refined registration of measured poses
  or points to a chain (base frame, tool frame or marker points);
* :mod:`estcal.intake.frames` — which (root, tip) links of a URDF the data measure
  (``estcal frames``);
* :mod:`estcal.intake.hygiene` — data hygiene before a fit: swapped marker labels, non-rigid
  rows, outliers, readings beyond the joint limits, repeated poses, duplicate rows, unused
  columns (``estcal check``).
"""
