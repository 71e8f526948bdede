"""The effect protocol, a base class and the registry of named effects.

An *effect* is a non-geometric error model whose parameters join the robot's
named parameter vector (:meth:`estcal.kinematics.SerialRobot.add_effect`).
It contributes either a joint-space correction ``δq (N, n)`` added to the
joint values, or a Cartesian correction ``δx (N, k, 3)`` added to the marker
points, together with the exact derivative of that correction with respect to
its own parameters. See ``docs/effects.md`` for the contract and how to add a
user effect.
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

__all__ = ["Effect", "JointEffect", "EFFECTS", "register_effect", "make_effect", "effect_context",
           "list_effects"]


class Effect:
    """Base class: joint selection, parameter naming and binding, serialisation.

    Subclasses set ``name`` (registry name), ``prefixes`` (parameter-name
    prefixes per selected joint, e.g. ``["compliance"]`` → ``compliance_<joint>``)
    and implement ``joint_correction`` or ``point_correction``.

    Parameters
    ----------
    robot : SerialRobot
        The robot the effect will be added to (joint names/types are read from it).
    joints : sequence of str, optional
        Joint names the effect acts on; default :meth:`default_joints`.
    """

    name = "effect"
    prefixes: tuple[str, ...] = ()
    allowed_types: tuple[str, ...] = ("revolute", "prismatic")

    def __init__(self, robot, joints: Sequence[str] | None = None):
        self.robot_joints = list(robot.joint_names)
        if joints is None:
            joints = self.default_joints(robot)
        elif isinstance(joints, str):
            joints = [j for j in joints.split(",") if j]
        joints = list(joints)
        for j in joints:
            if j not in robot.joint_names:
                raise ValueError(f"effect {self.name!r}: unknown joint {j!r}; the robot's joints are "
                                 f"{robot.joint_names}")
            jt = robot.joint_types[robot.joint_names.index(j)]
            if jt not in self.allowed_types:
                raise ValueError(f"effect {self.name!r}: joint {j!r} is {jt}; this effect applies to "
                                 f"{' and '.join(self.allowed_types)} joints only")
        if len(set(joints)) != len(joints):
            raise ValueError(f"effect {self.name!r}: joint listed twice in {joints}")
        self.joints = joints
        self.joint_index = np.array([robot.joint_names.index(j) for j in joints], int)
        self.indices = None

    def default_joints(self, robot) -> list[str]:
        return [j for j, t in zip(robot.joint_names, robot.joint_types) if t in self.allowed_types]

    # ------------------------------------------------------------- protocol
    @property
    def param_names(self) -> list[str]:
        return [f"{p}_{j}" for p in self.prefixes for j in self.joints]

    @property
    def param_frames(self) -> list[str]:
        return [j for _ in self.prefixes for j in self.joints]

    def initial_values(self) -> np.ndarray:
        """Nominal values: zero, i.e. the effect is absent."""
        return np.zeros(len(self.param_names))

    def bind(self, indices) -> None:
        self.indices = np.asarray(indices, int)

    def values(self, theta) -> np.ndarray:
        if self.indices is None:
            raise RuntimeError(f"effect {self.name!r} is not bound to a robot; use robot.add_effect(effect)")
        return np.asarray(theta, float)[self.indices]

    def context_keys(self) -> list[str]:
        """Per-pose context entries this effect reads (for :func:`effect_context`)."""
        return []

    def options(self) -> dict:
        """Constructor keyword options (besides ``joints``), for serialisation."""
        return {}

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"effect": self.name, "joints": list(self.joints)}
        if self.options():
            d["options"] = self.options()
        return d

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options().items())
        return f"{type(self).__name__}(joints={self.joints}{', ' + opts if opts else ''})"


class JointEffect(Effect):
    """An effect adding ``δq_j = Σ_p θ_{p,j} · f_p(j)`` — linear in its parameters.

    Subclasses implement ``features(robot, readings, q, theta, context) -> (N, n_prefixes, n_sel)``:
    the basis functions ``f_p`` for every prefix ``p`` and selected joint, so that
    ``δq[:, joint] = Σ_p θ[p, joint] · F[:, p, joint]`` and the derivative is ``F`` itself.
    """

    def features(self, robot, readings, q, theta, context) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def param_joints(self) -> np.ndarray:
        """(m,) the joint each parameter moves (parameter order is prefix-major): ``joint_correction``'s
        derivative is nonzero in that joint's row only, which the chain uses instead of the dense array."""
        return np.tile(self.joint_index, len(self.prefixes))

    def joint_correction(self, robot, readings, q, theta, context):
        N, n = q.shape
        m = len(self.param_names)
        if not len(self.joints):
            return np.zeros((N, n)), np.zeros((N, n, 0))
        F = self.features(robot, readings, q, theta, context)  # (N, P, s)
        P, s = len(self.prefixes), len(self.joints)
        w = self.values(theta).reshape(P, s)
        dq = np.zeros((N, n))
        dq[:, self.joint_index] = np.einsum("nps,ps->ns", F, w)
        # parameter order is prefix-major: index p*s + i belongs to joint i
        dd = np.zeros((N, n, m))
        cols = np.arange(m).reshape(P, s)
        for i, j in enumerate(self.joint_index):
            dd[:, j, cols[:, i]] = F[:, :, i]
        return dq, dd


# ----------------------------------------------------------------- registry
EFFECTS: dict[str, Callable[..., Effect]] = {}


def register_effect(name: str, factory: Callable[..., Effect], overwrite: bool = False) -> None:
    """Register ``factory(robot, joints=None, **options) -> effect`` under ``name``.

    The returned object must follow the protocol of :meth:`SerialRobot.add_effect`
    (``param_names``, ``initial_values()``, ``bind()``, and ``joint_correction`` or
    ``point_correction``); see ``docs/effects.md``.
    """
    if not name or not name.replace("_", "").isalnum():
        raise ValueError(f"effect names are identifiers (letters, digits, _), got {name!r}")
    if name in EFFECTS and not overwrite:
        raise ValueError(f"effect {name!r} is already registered (pass overwrite=True to replace it)")
    EFFECTS[name] = factory


def make_effect(name: str, robot, joints: Sequence[str] | None = None, **options) -> Effect:
    """Instantiate the registered effect ``name`` for ``robot`` (not yet added: use ``robot.add_effect``)."""
    try:
        factory = EFFECTS[name]
    except KeyError:
        import difflib

        close = difflib.get_close_matches(name, list(EFFECTS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown effect {name!r}{hint}; registered effects: {', '.join(sorted(EFFECTS))}") \
            from None
    return factory(robot, joints=joints, **options)


def list_effects() -> dict[str, str]:
    """Registered effect names with the first line of their docstring."""
    out = {}
    for k, f in sorted(EFFECTS.items()):
        doc = (getattr(f, "__doc__", None) or "").strip().splitlines()
        out[k] = doc[0] if doc else ""
    return out


def effect_context(robot, dataset=None, context: dict | None = None) -> dict:
    """Per-pose context for the robot's effects: ``dataset.context`` plus any extra
    dataset column an effect asks for (e.g. ``approach_j2`` for backlash)."""
    ctx = dict(context or {})
    if dataset is not None:
        ctx.update(getattr(dataset, "context", {}) or {})
        cols = getattr(dataset, "columns", {}) or {}
        for eff in robot.effects:
            for key in getattr(eff, "context_keys", lambda: [])():
                if key not in ctx and key in cols:
                    ctx[key] = np.asarray(cols[key], float)
    return ctx
