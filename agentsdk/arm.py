"""What a behavior needs to know about an arm it was not written for, derived from its kinematics.

The shipped behaviors (``square``, ``patrol``, ``pick_place``) run on any serial arm —
arm3, a UR5, a Panda, a robot nobody here wrote — because they ask these functions
instead of naming joints:

* :func:`end_effector`: the tool frame (a link named like one: ``tool0``, ``*_tcp``,
  ``ee_link``..., else the link moved by the most joints);
* :func:`arm_joints`: the joints that move it (``kin.chain``: a gripper's fingers and
  other branches are left out);
* :func:`ready_configuration`: a configuration near the start where the end effector is
  above the base, away from the joint limits and moves well in every direction (the
  product of the position Jacobian's singular values is largest);
* :func:`spread`: a configuration turned about the first arm joint (the "waist") and
  :func:`lowered`: one with the end effector moved straight down, both within the limits;
* :func:`layout_steps`: all of them at once, an :class:`ArmLayout` (home, left, right, and
  left/right lowered) for a pick-and-place or a patrol.

Everything is computed on the host from ``robot.kinematics`` (no simulator needed), and a
robot that cannot do what is asked raises :class:`~agentsdk.errors.UnreachablePoseError`
with one line saying why.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass
from typing import cast

import numpy as np

from .errors import UnreachablePoseError
from .kinematics import Kinematics, run_sync
from .types import FloatArray

__all__ = [
    "MIN_DROP",
    "TOOL_NAMES",
    "ArmLayout",
    "arm_joints",
    "end_effector",
    "layout_steps",
    "lowered",
    "ready_configuration",
    "ready_configuration_steps",
    "spread",
    "to_mapping",
]

#: the smallest drop :func:`layout_steps` accepts (m)
MIN_DROP = 0.01
_XY_WEIGHT = 0.2
#: link names (or ``_``-suffixes) that name a tool frame, most specific first
TOOL_NAMES = ("tool0", "tcp", "ee_link", "end_effector", "eef", "flange", "tool")


def end_effector(kin: Kinematics) -> str:
    """The tool frame: a link named like one (see :data:`TOOL_NAMES`), else the link moved by the most joints."""
    for link in reversed(kin.link_names):
        low = link.lower()
        if any(low == name or low.endswith("_" + name) for name in TOOL_NAMES):
            if kin.chain(link):
                return link
    return max(kin.link_names, key=lambda link: len(kin.chain(link)))


def arm_joints(kin: Kinematics, link: str) -> tuple[str, ...]:
    """The joints that move ``link``, in ``kin.joint_names`` order; raises when none does."""
    chain = kin.chain(link)
    if not chain:
        raise UnreachablePoseError(f"{kin.name}: no joint moves link {link!r}; this behavior needs an arm")
    return chain


def _bounds(kin: Kinematics, margin: float = 0.1) -> tuple[FloatArray, FloatArray]:
    """Joint bounds (±π where unlimited) pulled ``margin`` of each range inside the limits."""
    lo = np.where(np.isfinite(kin.lower), kin.lower, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, np.pi)
    pad = margin * (hi - lo)
    return lo + pad, hi - pad


def ready_configuration_steps(
    kin: Kinematics,
    link: str,
    start: FloatArray,
    *,
    full: bool = False,
    samples: int = 300,
    reach: float = 0.6,
    seed: int = 0,
) -> Generator[None, None, FloatArray]:
    """:func:`ready_configuration` as a cooperative computation (drive it with ``run_async``)."""
    chain = arm_joints(kin, link)
    idx = np.array([kin.joint_names.index(j) for j in chain], dtype=np.intp)
    lo, hi = _bounds(kin, 0.05)
    rng = np.random.default_rng(seed)
    start = np.asarray(start, dtype=float)
    best, best_q = -1.0, start
    for k in range(samples):
        yield
        q = start.copy()
        if k:
            q[idx] = np.clip(start[idx] + rng.uniform(-reach, reach, len(idx)), lo[idx], hi[idx])
        if kin.fk(link, q).position[2] < 0.0:
            continue
        jac = kin.jacobian(link, q)[:, idx]
        sv = np.linalg.svd(jac if full else jac[:3], compute_uv=False)
        # full pose: the smallest singular value (distance to a singularity); else the two largest
        score = float(sv[min(5, len(sv) - 1)]) if full else float(np.prod(sv[:2]))
        if score > best:
            best, best_q = score, q
    return best_q


def ready_configuration(
    kin: Kinematics,
    link: str,
    start: FloatArray,
    *,
    full: bool = False,
    samples: int = 300,
    reach: float = 0.6,
    seed: int = 0,
) -> FloatArray:
    """A well-conditioned configuration within ``reach`` rad of ``start`` (the other joints as in ``start``).

    Over ``samples`` reproducible random configurations of the arm joints within ``reach`` of
    ``start`` (so the move there stays short and away from self-collisions), 5 % of each range
    inside the limits, with the end effector above the root, picks the one farthest from a
    singularity (``full``: the largest smallest singular value of the 6-row Jacobian) or, for
    position only, where the end effector moves best in a plane (the product of the two largest
    singular values of the position Jacobian). A coroutine should use
    ``await run_async(ready_configuration_steps(...))`` (:func:`agentsdk.kinematics.run_async`),
    which keeps the control loop running.
    """
    return cast(FloatArray, run_sync(ready_configuration_steps(
        kin, link, start, full=full, samples=samples, reach=reach, seed=seed)))


def spread(kin: Kinematics, link: str, q: FloatArray, angle: float) -> FloatArray:
    """``q`` with the first arm joint turned by ``angle`` (rad), kept 10 % of its range inside its limits."""
    chain = arm_joints(kin, link)
    i = kin.joint_names.index(chain[0])
    lo, hi = _bounds(kin)
    out = np.array(q, dtype=float)
    out[i] = float(np.clip(out[i] + angle, lo[i], hi[i]))
    return out


def lowered(kin: Kinematics, link: str, q: FloatArray, drop: float, *, iterations: int = 50) -> FloatArray:
    """A configuration near ``q`` with ``link`` ``drop`` metres lower (damped least squares, within the limits).

    The end effector moves as straight down as the arm allows (the height has priority over the
    horizontal position: an arm whose reach is a sphere like arm3's drifts sideways); at least
    half of ``drop`` must be achieved, else :class:`UnreachablePoseError` says so.
    """
    chain = arm_joints(kin, link)
    idx = np.array([kin.joint_names.index(j) for j in chain], dtype=np.intp)
    lo, hi = _bounds(kin, 0.05)
    q = np.array(q, dtype=float)
    p0 = kin.fk(link, q).position
    goal = p0 - np.array([0.0, 0.0, drop])
    # the height first, the horizontal position second: an arm whose reach is a sphere (arm3) goes
    # down along the sphere instead of stopping at the point nearest the one straight below
    weight = np.array([_XY_WEIGHT, _XY_WEIGHT, 1.0])
    for _ in range(iterations):
        err = goal - kin.fk(link, q).position
        if abs(float(err[2])) < 1e-4 and float(np.linalg.norm(err)) < 1e-3:
            break
        jac = weight[:, None] * kin.jacobian(link, q)[:3, idx]
        dq = jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(3), weight * err)
        q[idx] = np.clip(q[idx] + np.clip(dq, -0.1, 0.1), lo[idx], hi[idx])
    achieved = float(p0[2] - kin.fk(link, q).position[2])
    if achieved < drop / 2:
        raise UnreachablePoseError(
            f"{kin.name}: link {link!r} can only be lowered by {achieved * 100:.1f} cm of the {drop * 100:.1f} cm "
            "asked near this configuration"
        )
    return q


@dataclass(frozen=True)
class ArmLayout:
    """Joint-space poses a pick-and-place or a patrol can use on this arm, all within its limits."""

    #: the end-effector link and the joints that move it
    link: str
    joints: tuple[str, ...]
    #: a well-conditioned configuration near the start (:func:`ready_configuration`)
    home: dict[str, float]
    #: ``home`` turned about the first arm joint by +/- the spread angle (:func:`spread`)
    left: dict[str, float]
    right: dict[str, float]
    #: ``left`` / ``right`` with the end effector lowered by the drop (:func:`lowered`)
    left_low: dict[str, float]
    right_low: dict[str, float]


def layout_steps(
    kin: Kinematics, start: FloatArray, *, angle: float = 0.8, drop: float = 0.05
) -> Generator[None, None, ArmLayout]:
    """An :class:`ArmLayout` around a ready configuration near ``start`` (cooperative: use ``run_async``).

    ``angle`` (rad) is the turn of the first arm joint to each side; ``drop`` (m) how far the end
    effector goes down there (halved where the arm cannot, down to :data:`MIN_DROP`, else
    :class:`UnreachablePoseError`).
    """
    link = end_effector(kin)
    joints = arm_joints(kin, link)
    home = yield from ready_configuration_steps(kin, link, start)
    left, right = spread(kin, link, home, angle), spread(kin, link, home, -angle)
    lows: list[FloatArray] = []
    for q in (left, right):
        step = drop
        while True:  # as far down as the arm goes there, halving the drop down to MIN_DROP
            yield
            try:
                lows.append(lowered(kin, link, q, step))
                break
            except UnreachablePoseError:
                if step / 2 < MIN_DROP:
                    raise
                step /= 2
    left_low, right_low = lows

    def m(q: FloatArray) -> dict[str, float]:
        return to_mapping(kin, q, joints)

    return ArmLayout(link, joints, m(home), m(left), m(right), m(left_low), m(right_low))


def to_mapping(kin: Kinematics, q: FloatArray, joints: tuple[str, ...]) -> dict[str, float]:
    """``{joint: position}`` of ``joints`` taken from the full configuration ``q``."""
    return {j: float(q[kin.joint_names.index(j)]) for j in joints}
