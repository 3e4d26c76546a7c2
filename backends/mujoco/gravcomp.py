"""Gravity compensation computed by MuJoCo inside the step: ``body_gravcomp`` routed through the actuators.

The servo law adds ``g(q)`` to each compensated joint's torque, clamped with it to the effort
limit (:mod:`agentsdk.backend`). MuJoCo can do that itself at every physics step, from the state
it integrates: a body with ``gravcomp = 1`` gets the force that cancels its weight, applied at its
centre of mass through the joints of its chain (``qfrc_gravcomp``: per dof the very ``g(q)``
of ``mj_rne`` at rest), and a joint with ``actuatorgravcomp`` adds its share to ``qfrc_actuator``
instead of the passive forces, where the joint's ``actuatorfrcrange`` clamps the sum of its
servo and gravity torque (the servo's own force range is then left open, so the clamp is
``clamp(servo + g(q))``, not ``clamp(clamp(servo) + g(q))``).
Nothing is computed on the host per tick, so a block of ticks can run as one MuJoCo call.

:class:`StepGravity` decides from the model's tree whether that fits the law exactly, sets the
model up, and switches the torque of disabled joints off (an e-stop, a joint's ``enabled``
flag) by clamping the joint's actuator force to ``[0, 0]``: servo and gravity torque together.

Where it does not fit, the backend keeps the host-side term (:class:`agentsdk.dynamics.GravityTerm`,
once per control period at the measured position): MuJoCo adds a body's ``gravcomp`` force to
every dof of its chain, and a free or ball joint's share cannot be clamped away (MuJoCo clamps
hinge and slide joints only), so a robot whose commanded joints move below a free or ball joint
(a floating base) would be held up by its own compensation; and a joint whose compensation is
off (robot.yaml ``gravity_compensation: {default: true, gripper: false}``) cannot be left out
of its ancestors' share of the same bodies.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import mujoco
import numpy as np

__all__ = ["StepGravity", "drop_model_gravcomp", "step_gravity_obstacle"]

_HINGE, _SLIDE = mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE
_LIMITED = mujoco.mjtLimited.mjLIMITED_TRUE
_UNLIMITED = mujoco.mjtLimited.mjLIMITED_FALSE


def _chains(spec: mujoco.MjSpec) -> list[tuple[mujoco.MjsBody, list[mujoco.MjsJoint]]]:
    """Every body but the world with the joints of its chain (its own and its ancestors')."""
    out: list[tuple[mujoco.MjsBody, list[mujoco.MjsJoint]]] = []
    stack: list[tuple[mujoco.MjsBody, list[mujoco.MjsJoint]]] = [(b, []) for b in spec.worldbody.bodies]
    while stack:
        body, above = stack.pop()
        chain = [*above, *body.joints]
        out.append((body, chain))
        stack.extend((child, chain) for child in body.bodies)
    return out


def step_gravity_obstacle(spec: mujoco.MjSpec, carried: Sequence[str]) -> str | None:
    """Why MuJoCo's gravity compensation cannot carry ``g(q)`` of the joints ``carried``, or None when it can.

    ``carried``: the commanded joints and the joints that follow them (mimic joints). A body
    whose chain holds one of them and a free or ball joint gets the reason.
    """
    names = set(carried)
    for body, chain in _chains(spec):
        if any(j.name in names for j in chain):
            other = next((j for j in chain if j.type not in (_HINGE, _SLIDE)), None)
            if other is not None:
                kind = "free" if other.type == mujoco.mjtJoint.mjJNT_FREE else "ball"
                return (f"body {body.name!r} moves with the {kind} joint {other.name!r}, whose share of its "
                        "gravity compensation MuJoCo cannot leave out")
    return None


def drop_model_gravcomp(spec: mujoco.MjSpec, compensated: Sequence[str]) -> list[str]:
    """Clear the model's own ``gravcomp`` of every body that moves with one of the joints ``compensated``.

    For the host route: the servo law's ``g(q)`` (computed on the host, the full weight of those
    bodies) already holds them, so an MJCF's ``gravcomp`` on them would hold them a second time.
    Bodies that move with none of them keep the model's value. Returns the names of the bodies cleared.
    """
    names = set(compensated)
    cleared: list[str] = []
    for body, chain in _chains(spec):
        if body.gravcomp != 0.0 and any(j.name in names for j in chain):
            body.gravcomp = 0.0
            cleared.append(body.name)
    return cleared


class StepGravity:
    """MuJoCo's own gravity compensation for the commanded joints (see the module docstring).

    :meth:`configure` sets up the spec before it is compiled (the servo actuators must exist,
    named ``<joint>_servo``); :meth:`bind` takes the compiled model. Joint ``k`` (commanded
    order) gets ``g(q)`` of every body moving with it, clamped with its servo torque to
    ``±max_effort[k]``; a mimic follower gets its own share (its leader carries it through the
    joint equality, as the host term adds it to the leader), clamped with its leader's torque
    off. Other joints of those bodies' chains get none (their actuator force is clamped to 0:
    they have no actuator); bodies and joints that move with no commanded joint are left as the
    model has them. :meth:`set_enabled` and :meth:`torque_off` switch joints' torque off and on.
    """

    def __init__(self, joints: Sequence[str], followers: Mapping[str, str], max_effort: np.ndarray) -> None:
        self.joints = tuple(joints)
        #: {follower joint: its leader}, leaders among ``joints``
        self.followers = dict(followers)
        self.max_effort = np.asarray(max_effort, dtype=float)
        #: the other joints of the carried chains (set up by configure)
        self._passive: list[mujoco.MjsJoint] = []

    def configure(self, spec: mujoco.MjSpec) -> None:
        """Give the carried bodies ``gravcomp = 1`` and route it through the joints' actuator force limits."""
        carried = set(self.joints) | set(self.followers)
        self._passive.clear()

        def visit(body: mujoco.MjsBody, moving: bool) -> bool:
            """Set up ``body``'s subtree; True when a carried body is in it (its joints then route g(q))."""
            moving = moving or any(j.name in carried for j in body.joints)
            if moving:
                body.gravcomp = 1.0  # (a body moving with no commanded joint keeps the model's own value)
            below = [visit(child, moving) for child in body.bodies]
            if moving or any(below):
                for joint in body.joints:  # hinge and slide only (step_gravity_obstacle)
                    self._route(joint)
            return moving or any(below)

        for top in spec.worldbody.bodies:
            visit(top, False)
        for name in self.joints:  # the joint's limit clamps servo + g(q); the servo's own range would clamp twice
            act = spec.actuator(f"{name}_servo")
            act.forcelimited = _UNLIMITED

    def _route(self, joint: mujoco.MjsJoint) -> None:
        """``joint``'s share of the compensation into its actuator force, clamped as the law says."""
        joint.actgravcomp = 1
        if joint.name in self.joints:
            effort = float(self.max_effort[self.joints.index(joint.name)])
            if np.isfinite(effort):
                joint.actfrclimited, joint.actfrcrange = _LIMITED, [-effort, effort]
            else:
                joint.actfrclimited = _UNLIMITED
        elif joint.name in self.followers:
            joint.actfrclimited = _UNLIMITED
        else:  # no actuator: its actuator force is its gravity share alone, which the law leaves out
            self._passive.append(joint)  # clamped to [0, 0] in bind (the compiler wants a range; may be unnamed)

    def bind(self, model: mujoco.MjModel) -> None:
        """Take the compiled model: the joint rows switched per commanded joint and their nominal limits."""
        self._limited = model.jnt_actfrclimited  # views (model arrays MuJoCo reads at every step)
        self._range = model.jnt_actfrcrange
        self._rows: list[np.ndarray] = []
        for name in self.joints:
            ids = [model.joint(name).id] + [model.joint(f).id for f, leader in self.followers.items() if leader == name]
            self._rows.append(np.array(ids, dtype=np.intp))
        for joint in self._passive:  # (a spec element's id is the compiled model's)
            self._limited[joint.id] = 1
            self._range[joint.id] = 0.0
        self._nominal_limited = np.array(model.jnt_actfrclimited, copy=True)
        self._nominal_range = np.array(model.jnt_actfrcrange, copy=True)
        #: the ``enabled`` bytes the limits were last set for (empty: set them at the next write)
        self._applied = b""

    def set_enabled(self, enabled: np.ndarray, key: bytes) -> None:
        """Joint ``k``'s torque (servo and gravity) off where ``enabled[k]`` is False, else at its limit.

        ``key``: ``enabled.tobytes()``; nothing to do when it is what it was at the last call.
        """
        if key == self._applied:
            return
        for k, rows in enumerate(self._rows):
            if enabled[k]:
                self._limited[rows] = self._nominal_limited[rows]
                self._range[rows] = self._nominal_range[rows]
            else:
                self._limited[rows] = 1
                self._range[rows] = 0.0
        self._applied = key

    def torque_off(self) -> None:
        """Every commanded joint's torque off now (an e-stop; plain stores: thread-safe enough)."""
        self._applied = b""  # the next set_enabled sets the limits again
        for rows in self._rows:
            self._limited[rows] = 1
            self._range[rows] = 0.0

    def effort_limit(self, k: int) -> float:
        """Joint ``k``'s effort limit as compiled (inf when unlimited)."""
        row = int(self._rows[k][0])
        return float(self._nominal_range[row, 1]) if self._nominal_limited[row] else float("inf")
