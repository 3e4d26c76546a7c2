"""An MJCF model at its start pose: the contacts it starts in, its ground, where a floating base stands.

The rules the URDF path applies (:mod:`agentsdk.description.collision`), expressed on a
compiled MuJoCo model so that an MJCF file keeps its own contact settings otherwise:

* **touching at the start pose**: two bodies of the robot whose geoms are within
  :data:`~agentsdk.description.collision.TOUCH_DISTANCE` of each other at the start pose
  (and that MuJoCo would collide: contype/conaffinity, excludes and its parent filter
  applied) do not collide - they would be stuck together from the first step. This
  includes bodies welded to the world (a mounted arm's base), which MuJoCo's parent filter
  does not cover. Only bodies of one tree (the same child of the world) are paired: a
  robot never loses its contact with a floor, a table or another object of the scene;
* **ground**: a model has one when a plane or height field is attached to the world;
* **standing**: a floating base without ground is placed so that its lowest collision
  shape touches the ground plane ``z = 0`` that the simulator adds. That plane collides with
  every geom that takes part in contacts (any contype/conaffinity bit); a robot none of whose
  geoms does (a main file whose contacts are the scene file's explicit ``<pair>`` elements,
  e.g. Menagerie's Apollo) stands on it through explicit pairs with its collision shapes
  (:func:`ground_geoms`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .collision import TOUCH_DISTANCE, lowest_point

__all__ = [
    "COLLISION_GROUP", "collision_geoms", "ground_geoms", "has_ground", "standing_offset", "start_qpos",
    "touching_at_start",
]

#: the first geom group MuJoCo's viewer hides by default: where models keep their collision shapes by convention
COLLISION_GROUP = 3

Pair = tuple[str, str]


def _body_name(model: Any, body: int) -> str:
    import mujoco

    return "world" if body == 0 else (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or "")


def has_ground(model: Any) -> bool:
    """True when a plane or height field is attached to the world (the scene's floor)."""
    import mujoco

    kinds = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD))
    return any(
        int(model.geom_type[g]) in kinds and int(model.body_weldid[model.geom_bodyid[g]]) == 0
        for g in range(model.ngeom)
    )


def collision_geoms(model: Any, body_root: int | None = None) -> list[int]:
    """Geoms that take part in contacts (contype or conaffinity set), of one tree (``body_root``) or all."""
    return [
        g
        for g in range(model.ngeom)
        if (model.geom_contype[g] or model.geom_conaffinity[g])
        and int(model.geom_bodyid[g]) != 0
        and (body_root is None or int(model.body_rootid[model.geom_bodyid[g]]) == body_root)
    ]


def ground_geoms(model: Any, body_root: int) -> tuple[list[int], bool]:
    """The geoms of one tree that stand on the ground plane the simulator adds, and whether they need explicit pairs.

    The tree's :func:`collision_geoms` (the plane collides with any contype/conaffinity bit),
    ``False``; when it has none (every geom contype = conaffinity = 0: the model's contacts
    are explicit pairs in a scene file), its collision shapes by MuJoCo's convention (geom
    group :data:`COLLISION_GROUP` and up), else all its geoms, ``True``: the simulator pairs
    them with the plane.
    """
    own = collision_geoms(model, body_root)
    if own:
        return own, False
    tree = [
        g for g in range(model.ngeom)
        if int(model.geom_bodyid[g]) != 0 and int(model.body_rootid[model.geom_bodyid[g]]) == body_root
    ]
    hidden = [g for g in tree if int(model.geom_group[g]) >= COLLISION_GROUP]
    return (hidden or tree), True


def start_qpos(
    model: Any,
    data: Any,
    positions: dict[str, float],
    keyframe: str | None,
    mimics: list[tuple[str, str, float, float]],
) -> None:
    """Put ``data`` at the start pose: the keyframe (else the model's reference pose), then the joints.

    ``mimics``: ``(follower, leader, multiplier, offset)`` joint couplings applied after.
    Runs ``mj_kinematics``.
    """
    import mujoco

    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, keyframe) if keyframe else -1
    if key >= 0:
        mujoco.mj_resetDataKeyframe(model, data, key)
    else:
        mujoco.mj_resetData(model, data)
    for name, q in positions.items():
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0 and math.isfinite(q):
            data.qpos[model.jnt_qposadr[jid]] = q
    for follower, leader, mult, offset in mimics:
        jf = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, follower)
        jl = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, leader)
        if jf >= 0 and jl >= 0:
            data.qpos[model.jnt_qposadr[jf]] = offset + mult * data.qpos[model.jnt_qposadr[jl]]
    mujoco.mj_kinematics(model, data)


def touching_at_start(model: Any, data: Any) -> set[Pair]:
    """Body pairs of one tree in contact (within TOUCH_DISTANCE) at ``data``'s pose, as MuJoCo would collide them.

    ``data`` holds the start pose (:func:`start_qpos`); ``model`` is not changed (a copy
    with widened margins finds the contacts). Unnamed bodies are left out (they cannot be
    named in an ``<exclude>``).
    """
    import copy

    import mujoco

    probe = copy.copy(model)
    probe.geom_margin[:] = np.maximum(probe.geom_margin, TOUCH_DISTANCE)
    probe.geom_gap[:] = 0.0
    scratch = mujoco.MjData(probe)
    scratch.qpos[:] = data.qpos
    mujoco.mj_kinematics(probe, scratch)
    mujoco.mj_collision(probe, scratch)
    out: set[Pair] = set()
    for c in scratch.contact[: scratch.ncon]:
        b1, b2 = int(probe.geom_bodyid[c.geom1]), int(probe.geom_bodyid[c.geom2])
        if b1 == 0 or b2 == 0 or b1 == b2 or probe.body_rootid[b1] != probe.body_rootid[b2]:
            continue
        if c.dist > TOUCH_DISTANCE:
            continue
        n1, n2 = _body_name(probe, b1), _body_name(probe, b2)
        if n1 and n2:
            out.add((n1, n2) if n1 <= n2 else (n2, n1))
    return out


def standing_offset(model: Any, data: Any, body: int) -> float:
    """How far (m) to raise the tree of ``body`` so that its lowest ground contact shape touches ``z = 0``.

    The shapes are :func:`ground_geoms`.
    """
    lowest = lowest_point(model, data, ground_geoms(model, int(model.body_rootid[body]))[0])
    return 0.0 if not math.isfinite(lowest) else -lowest
