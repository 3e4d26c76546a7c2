"""What PyBullet can simulate of an MJCF model: what it drops (with why) and what it cannot load.

PyBullet loads a URDF made from the description (:mod:`agentsdk.description.mjcf` reads the MJCF);
this module compiles the MJCF once more with MuJoCo and names every element a URDF cannot carry.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from .mjcf import _compile, free_root
from .model import RobotDescription

__all__ = ["mjcf_dropped_by_pybullet", "mjcf_pybullet_fit", "mjcf_unsupported_by_pybullet"]


def _tendon_passive(m: Any, t: int) -> list[str]:
    """What tendon ``t`` does by itself, without an actuator (empty: it only transmits an actuator's force)."""
    out: list[str] = []
    if m.tendon_limited[t]:
        out.append("a length range")
    for attr, what in (
        ("tendon_stiffness", "stiffness"),
        ("tendon_damping", "damping"),
        ("tendon_frictionloss", "friction loss"),
        ("tendon_armature", "armature"),
    ):
        values = getattr(m, attr, None)
        if values is not None and float(np.abs(np.asarray(values[t])).max()) > 0.0:
            out.append(what)
    return out


def _eq_body(m: Any, e: int, which: int) -> int:
    """The body equality ``e``'s object ``which`` (1 or 2) sits on (a site's body; 0: the world)."""
    import mujoco

    obj = int(m.eq_obj1id[e] if which == 1 else m.eq_obj2id[e])
    if obj < 0:
        return 0
    if int(m.eq_objtype[e]) == int(mujoco.mjtObj.mjOBJ_SITE):
        return int(m.site_bodyid[obj])
    return obj


def mjcf_pybullet_fit(description: RobotDescription) -> tuple[list[str], list[str]]:
    """(what PyBullet drops, what it cannot load) of an MJCF model, one compile for both.

    See :func:`mjcf_dropped_by_pybullet` and :func:`mjcf_unsupported_by_pybullet`.
    """
    import mujoco

    _, m = _compile(description.source)
    dropped: list[str] = []
    out: list[str] = []
    obj = mujoco.mjtObj
    free = [j for j in description.all_joints if j.type == "floating"]
    if free and not (len(free) == 1 and free_root(description) is not None):
        out.append(f"free joints other than one at the root ({', '.join(j.name for j in free)})")
    elif free and any(not m.body(int(m.jnt_bodyid[j])).name for j in range(m.njnt)
                      if int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)):
        # the floating step matches the body between the two simulators by its name
        out.append(f"a free joint on an unnamed body ({free[0].child!r} here; give the <body> a name)")
    kinds = {j.type for j in description.all_joints}
    if "ball" in kinds:
        out.append("ball joints")
    for t in range(m.ntendon):
        name = mujoco.mj_id2name(m, obj.mjOBJ_TENDON, t) or f"#{t}"
        wraps = m.wrap_type[m.tendon_adr[t] : m.tendon_adr[t] + m.tendon_num[t]]
        kind = "fixed" if all(int(w) == int(mujoco.mjtWrap.mjWRAP_JOINT) for w in wraps) else "spatial"
        passive = _tendon_passive(m, t)
        if passive:
            out.append(f"{kind} tendon {name!r} with {', '.join(passive)}")
        else:
            dropped.append(
                f"{kind} tendon {name!r} (it only transmits the model's actuator, which the SDK's servos replace: "
                "each of its joints is commanded on its own, as on MuJoCo)"
            )
    body = functools.partial(mujoco.mj_id2name, m, obj.mjOBJ_BODY)
    other_eq: list[str] = []
    for e in range(m.neq):
        eq_kind = int(m.eq_type[e])
        name = mujoco.mj_id2name(m, obj.mjOBJ_EQUALITY, e)
        label = f"{mujoco.mjtEq(eq_kind).name.removeprefix('mjEQ_').lower()}" + (f" {name!r}" if name else f" #{e}")
        if eq_kind == int(mujoco.mjtEq.mjEQ_JOINT) and m.eq_obj2id[e] >= 0:
            continue  # a joint coupling: a mimic joint, a gear constraint on PyBullet
        if eq_kind in (int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_WELD)):
            b1, b2 = _eq_body(m, e, 1), _eq_body(m, e, 2)
            w1, w2 = int(m.body_weldid[b1]), int(m.body_weldid[b2])
            mocap = int(m.body_mocapid[b1]) >= 0 or int(m.body_mocapid[b2]) >= 0
            if w1 != 0 and w2 != 0 and w1 != w2 and not mocap:  # between two moving parts of the robot: a loop
                dropped.append(
                    f"{label} constraint between bodies {body(b1)!r} and {body(b2)!r} (it closes a linkage; "
                    "PyBullet simulates the chain open: each joint of the loop is held by its own servo, so the "
                    "linkage keeps its shape while the commanded positions agree with it, and a command that "
                    "does not moves the joints apart where MuJoCo's constraint would hold the loop together)"
                )
                continue
        other_eq.append(label)
    if other_eq:
        out.append(f"equality constraints other than joint coupling or linkage closure ({', '.join(other_eq)})")
    names = {mujoco.mjtGeom(t).name.removeprefix("mjGEOM_").lower() for t in m.geom_type}
    odd = sorted(
        names
        - {"sphere", "capsule", "cylinder", "box", "mesh"}
        - ({"plane"} if all(m.geom_bodyid[g] == 0 for g in range(m.ngeom) if m.geom_type[g] == 0) else set())
    )
    if odd:
        out.append(f"geom types {', '.join(odd)}")
    if m.nflex:
        out.append("flexes")
    return dropped, out


def mjcf_unsupported_by_pybullet(description: RobotDescription) -> list[str]:
    """What of an MJCF model a URDF for PyBullet cannot carry (empty: it can be loaded as a URDF).

    A free joint on the one body attached to the world is a floating base (:func:`free_root`);
    other free joints (several floating bodies, a free joint below another body) have no URDF form.
    Tendons with a length range, stiffness, damping, friction loss or armature act by themselves and
    have no URDF form; tendons without (they only transmit an actuator's force) are dropped instead
    (:func:`mjcf_dropped_by_pybullet`), as are connect and weld constraints that close a linkage.
    """
    return mjcf_pybullet_fit(description)[1]


def mjcf_dropped_by_pybullet(description: RobotDescription) -> list[str]:
    """What PyBullet leaves out of an MJCF model and why, one entry per element (empty: nothing).

    * a tendon that only transmits the model's actuator (no length range, stiffness, damping,
      friction loss or armature): the SDK replaces the model's actuators by its servos and commands
      each joint on its own, on MuJoCo too, so the tendon does nothing there either;
    * a ``connect`` or ``weld`` equality between two moving bodies of the robot (a loop closure, e.g.
      a four-bar gripper linkage): a URDF is a tree, so the chain is simulated open and each of its
      joints is held by its own servo.
    """
    return mjcf_pybullet_fit(description)[0]
