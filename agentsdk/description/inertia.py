"""Mass-property repairs, applied once in the description so every simulator gets the same masses.

Real exporters write inertias no simulator can take: tensors with slightly
negative eigenvalues, principal moments that violate the triangle inequality
``A + B >= C``, moving links with no mass at all. MuJoCo refuses such files
("inertia must satisfy A + B >= C", "inertia must have positive eigenvalues",
"mass and inertia of moving bodies must be larger than mjMINVAL"); PyBullet
silently zeroes a bad tensor and the joint then never moves. The rules below
are MuJoCo's own compiler rules (``src/user/user_objects.cc``,
``mjCBody::Compile`` and ``mjCModel``'s moving-body check), applied here once:

1. The tensor is diagonalised; principal moments that are negative only by
   round-off (``|m| <= 1e-9 * max``) become 0, really negative ones are
   clamped to 0 (a repair).
2. *boundmass / boundinertia*: a **moving** link (its parent joint is
   revolute, continuous or prismatic) whose mass is below :data:`MIN_MASS` or
   whose smallest principal moment is below :data:`MIN_INERTIA` is raised to
   those bounds - unless one of its direct children is rigidly attached (a
   fixed joint) and has mass and inertia above the bounds, which MuJoCo accepts
   (the child carries the body).
3. *balanceinertia*: principal moments that violate ``A + B >= C`` are all set
   to their mean. A violation within round-off (``1e-9`` relative) is closed
   exactly instead (``C = A + B``), which changes nothing physical.

Every change is returned as a :class:`~agentsdk.description.model.Repair`.
Repaired inertials are written in their principal frame (diagonal tensor,
``rpy`` of the principal axes), so neither simulator diagonalises again.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from .model import Inertial, JointRecord, LinkRecord, Repair, rpy_from_rotation

__all__ = ["MIN_INERTIA", "MIN_MASS", "repair_inertials"]

#: lower bound on the mass of a moving link (kg), MuJoCo's ``boundmass`` as applied here
MIN_MASS = 1e-5
#: lower bound on each principal moment of inertia of a moving link (kg·m²), MuJoCo's ``boundinertia``
MIN_INERTIA = 1e-10

_ROUNDOFF = 1e-9
#: principal moments below this (kg·m², MuJoCo's mjEPS) are numerical zeros, not data
_ZERO = 1e-14


def _g(v: float) -> str:
    return f"{v:.4g}"


def _moments(m: tuple[float, float, float]) -> str:
    return "(" + ", ".join(_g(x) for x in m) + ")"


def _principal_inertial(mass: float, xyz: tuple[float, float, float], rot: np.ndarray,
                        moments: tuple[float, float, float]) -> Inertial:
    return Inertial(
        mass=mass,
        xyz=xyz,
        rpy=rpy_from_rotation(rot),
        inertia=(moments[0], 0.0, 0.0, moments[1], 0.0, moments[2]),
    )


def _valid(inertial: Inertial | None) -> bool:
    if inertial is None:
        return False
    moments, _ = inertial.principal()
    return inertial.mass >= MIN_MASS and min(moments) >= MIN_INERTIA


def repair_inertials(
    links: Mapping[str, LinkRecord],
    joints: Mapping[str, JointRecord],
    lines: Mapping[str, int | None],
) -> tuple[dict[str, LinkRecord], list[Repair]]:
    """Apply the rules of the module docstring to every link.

    ``joints`` maps each child link to its parent joint; ``lines`` gives each
    link's line in the file. Returns the repaired link records (unchanged
    records are returned as they are) and the repairs made.
    """
    notes_of: dict[str, list[str]] = {}
    out: dict[str, LinkRecord] = {}
    # pass 1: tensor validity (rules 1 and 3), every link
    for name, rec in links.items():
        inertial = rec.inertial
        if inertial is None:
            out[name] = rec
            continue
        moments, rot = inertial.principal()
        top = max(abs(m) for m in moments)
        notes: list[str] = []
        fixed = list(moments)
        floor = max(_ZERO, _ROUNDOFF * top)
        negative = [m for m in fixed if m < -floor]
        if negative:
            notes.append(f"negative principal moment{'s' if len(negative) > 1 else ''} "
                         f"{', '.join(_g(m) for m in negative)} clamped to 0")
        fixed = [0.0 if m < floor else m for m in fixed]
        a, b, c = sorted(fixed)
        if a + b < c:
            if c - (a + b) <= _ROUNDOFF * c:
                fixed = [a, b, a + b]
            else:
                mean = (a + b + c) / 3.0
                notes.append(
                    f"principal moments {_moments((a, b, c))} violate A + B >= C: set to their mean {_g(mean)} "
                    "(MuJoCo balanceinertia)"
                )
                fixed = [mean, mean, mean]
                rot = np.eye(3) if inertial.rpy == (0.0, 0.0, 0.0) else rot
        changed = tuple(fixed) != tuple(moments) or any(inertial.inertia[k] != 0.0 for k in (1, 2, 4))
        if changed or notes:
            new = _principal_inertial(inertial.mass, inertial.xyz, rot, (fixed[0], fixed[1], fixed[2]))
            out[name] = LinkRecord(name, new, rec.visuals, rec.collisions, rec.inertial_as_written or inertial)
            if notes:
                notes_of.setdefault(name, []).extend(notes)
        else:
            out[name] = rec

    # pass 2: moving links need mass and inertia (rule 2)
    children: dict[str, list[str]] = {}
    for child, joint in joints.items():
        children.setdefault(joint.parent, []).append(child)
    for name, rec in list(out.items()):
        moving = joints.get(name)
        if moving is None or not moving.movable or _valid(rec.inertial):
            continue
        carried = any(
            joints[c].type == "fixed" and _valid(out[c].inertial) for c in children.get(name, ())
        )
        if carried:
            continue
        inertial = rec.inertial
        if inertial is None:
            mass, xyz, rot, moments = 0.0, (0.0, 0.0, 0.0), np.eye(3), (0.0, 0.0, 0.0)
        else:
            moments, rot = inertial.principal()
            mass, xyz = inertial.mass, inertial.xyz
        new_mass = max(mass, MIN_MASS)
        new_moments: tuple[float, float, float] = (
            max(moments[0], MIN_INERTIA), max(moments[1], MIN_INERTIA), max(moments[2], MIN_INERTIA)
        )
        a, b, c = sorted(new_moments)
        if a + b < c:  # raising the small moments cannot break the inequality, but stay exact
            new_moments = (a, b, a + b) if c - (a + b) <= _ROUNDOFF * c else new_moments
        if inertial is None:
            what, became = "has no <inertial>", f"mass {_g(new_mass)} kg, moments {_moments(new_moments)}"
        elif new_mass != mass:
            what = f"has mass {_g(mass)} kg, principal moments {_moments(moments)}"
            became = f"mass {_g(new_mass)} kg, moments {_moments(new_moments)}"
        else:
            what, became = f"has principal moments {_moments(moments)}", f"moments {_moments(new_moments)}"
        detail = (
            f"moving link (joint '{moving.name}') {what}: raised to {became} "
            f"(MuJoCo boundmass={_g(MIN_MASS)}, boundinertia={_g(MIN_INERTIA)})"
        )
        notes_of.setdefault(name, []).append(detail)
        new = _principal_inertial(new_mass, xyz, rot, (new_moments[0], new_moments[1], new_moments[2]))
        out[name] = LinkRecord(name, new, rec.visuals, rec.collisions, rec.inertial_as_written or inertial)
    assert all(math.isfinite(r.mass) for r in out.values())
    repairs = [
        Repair(f"link '{name}'", "; ".join(notes_of[name]), lines.get(name)) for name in links if name in notes_of
    ]
    return out, repairs
