"""Non-geometric effects (joint compliance, backlash, gear harmonics, encoder gain,
thermal expansion, drift, link tilt) and the registry for user effects.

>>> from estcal.kinematics import puma560
>>> from estcal.effects import make_effect
>>> robot = puma560()
>>> robot = robot.add_effect(make_effect("joint_compliance", robot, joints=["j2", "j3"]))
>>> [n for n in robot.params.names if n.startswith("compliance")]
['compliance_j2', 'compliance_j3']

See ``docs/effects.md`` for the formulas and the protocol for writing your own.
"""
from .base import EFFECTS, Effect, JointEffect, effect_context, list_effects, make_effect, register_effect
from .library import Backlash, Drift, EncoderGain, GearHarmonic, JointCompliance, LinkTilt, ThermalExpansion

__all__ = ["EFFECTS", "Effect", "JointEffect", "make_effect", "register_effect", "effect_context", "list_effects",
           "JointCompliance", "Backlash", "GearHarmonic", "EncoderGain", "ThermalExpansion", "Drift", "LinkTilt"]
