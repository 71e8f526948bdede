"""Robot models: transforms, the named parameter vector, serial chains and built-in robots."""
from .chain import Kinematics, Link, SerialRobot
from .parameters import ParameterError, ParameterVector
from .robots import BUILTIN, get_builtin, planar2, puma560, puma560_fu, robot_5r1p, stanford, tiago

__all__ = ["SerialRobot", "Kinematics", "Link", "ParameterVector", "ParameterError", "BUILTIN", "get_builtin",
           "stanford", "puma560", "puma560_fu", "robot_5r1p", "planar2", "tiago"]
