"""Inverse kinematics on the host-side model: mink's differential IK (a QP solved by DAQP) iterated
to convergence, with random restarts; and the cooperative runners that let a coroutine compute
it without starving the event loop.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Generator, Mapping
from typing import Any, Protocol

import mujoco
import numpy as np
import numpy.typing as npt

from .errors import InvalidValueError, UnreachablePoseError
from .hostmodel import Positions, wxyz_to_xyzw
from .pose import Pose, quat_multiply, rotation_vector
from .types import FloatArray, JointInfo

#: IK defaults: convergence tolerances (10x tighter than what users usually ask for)
IK_POSITION_TOLERANCE = 1e-4


IK_ORIENTATION_TOLERANCE = 1e-3


#: wall time a coroutine computes IK before yielding to the event loop (s)
_SLICE = 0.002


def run_sync(gen: Generator[None, None, Any]) -> Any:
    """Run a cooperative computation (a generator that yields between steps) to completion."""
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value


async def run_async(gen: Generator[None, None, Any], slice_s: float = _SLICE) -> Any:
    """Run a cooperative computation, yielding to the event loop every ``slice_s`` seconds of wall time.

    In lockstep, simulated time stays frozen meanwhile (this task stays ready), so the result and
    the robot's motion do not depend on the machine's speed; in realtime the control loop and the
    watchdogs keep running.
    """
    t0 = time.perf_counter()
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value
        now = time.perf_counter()
        if now - t0 >= slice_s:
            await asyncio.sleep(0)
            t0 = time.perf_counter()


class IKResult(dict[str, float]):
    """Joint positions found by :meth:`Kinematics.ik`: a ``{joint: position}`` dict, plus diagnostics.

    ``ok`` is True for a solution within the tolerances; :meth:`Kinematics.ik` raises
    :class:`UnreachablePoseError` (carrying the best attempt, ``ok == False``) otherwise,
    so a returned result is always a solution. ``position_error`` (m) and
    ``orientation_error`` (rad, 0 for position-only) are the residual at the solution.
    """

    ok: bool
    position_error: float
    orientation_error: float
    iterations: int
    attempts: int
    message: str

    def __init__(
        self,
        positions: Mapping[str, float],
        *,
        ok: bool,
        position_error: float,
        orientation_error: float,
        iterations: int,
        attempts: int,
        message: str = "",
    ) -> None:
        super().__init__(positions)
        self.ok = ok
        self.position_error = position_error
        self.orientation_error = orientation_error
        self.iterations = iterations
        self.attempts = attempts
        self.message = message

    def __repr__(self) -> str:
        vals = ", ".join(f"{k!r}: {v:.6g}" for k, v in self.items())
        return (
            f"IKResult({{{vals}}}, ok={self.ok}, position_error={self.position_error:.3g}, "
            f"orientation_error={self.orientation_error:.3g}, iterations={self.iterations}, attempts={self.attempts})"
        )


class IKModel(Protocol):
    """What the IK search needs from the kinematic model (implemented by :class:`~agentsdk.kinematics.Kinematics`)."""

    name: str
    model: mujoco.MjModel
    joints: tuple[JointInfo, ...]
    joint_names: tuple[str, ...]
    root_link: str
    lower: FloatArray
    upper: FloatArray
    _qadr: np.ndarray
    _frozen_dofs: list[int]

    def body_id(self, link: str) -> int:
        """The model's body id of ``link``."""

    def resolve(self, positions: Any = None, what: str = "positions") -> FloatArray:
        """Positions of every actuated joint, in joint order."""

    def _qpos(self, q: FloatArray, out: FloatArray) -> None:
        """Write the model's qpos of joint positions ``q`` (mimic joints follow) into ``out``."""

    def _solver(self) -> IKSolver:
        """The model's IK solver (made on first use)."""


def ik_target(pose: Pose | npt.ArrayLike, position_only: bool) -> tuple[Pose, bool]:
    """An IK target as a :class:`Pose` (a bare 3-vector is a position-only target) and its mode."""
    if isinstance(pose, Pose):
        return pose, bool(position_only)
    try:
        arr = np.asarray(pose, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidValueError(f"ik: expected a Pose, a 4x4 matrix or a position (3,), got {pose!r}") from exc
    if arr.shape == (3,):
        return Pose(arr), True
    if arr.shape == (4, 4):
        return Pose.from_matrix(arr), bool(position_only)
    raise InvalidValueError(f"ik: expected a Pose, a 4x4 matrix or a position (3,), got shape {arr.shape}")


class IKSolver:
    """mink differential IK iterated to convergence (one per Kinematics, used under its lock)."""

    def __init__(self, kin: IKModel) -> None:
        import mink

        self._mink = mink
        self.kin = kin
        m = kin.model
        self.conf = mink.Configuration(m)
        self.limits = [mink.ConfigurationLimit(m, gain=0.5)]
        constraints: list[Any] = []
        if kin._frozen_dofs:
            constraints.append(mink.DofFreezingTask(m, dof_indices=kin._frozen_dofs))
        if m.neq > 0 and any(m.eq_active0):
            constraints.append(mink.EqualityConstraintTask(m, cost=1.0))
        self.constraints = constraints
        self._tasks: dict[tuple[int, bool], Any] = {}
        self._qpos = np.zeros(m.nq)

    def _task(self, link: str, bid: int, position_only: bool) -> Any:
        key = (bid, position_only)
        task = self._tasks.get(key)
        if task is None:
            task = self._mink.FrameTask(
                frame_name=link, frame_type="body", position_cost=1.0,
                orientation_cost=0.0 if position_only else 1.0, lm_damping=1e-6,
            )
            self._tasks[key] = task
        return task

    def solve(
        self,
        bid: int,
        link: str,
        target: Pose,
        start: FloatArray,
        position_only: bool,
        ptol: float,
        rtol: float,
        max_iterations: int,
    ) -> Generator[None, None, tuple[FloatArray, float, float, int]]:
        """Iterate from ``start`` (yielding after each step); return ``(q, pos. error, orient. error, iterations)``."""
        mink = self._mink
        kin = self.kin
        conf = self.conf
        data = conf.data
        kin._qpos(start, self._qpos)
        conf.update(self._qpos)
        task = self._task(link, bid, position_only)
        wxyz = np.array([target.orientation[3], *target.orientation[:3]])
        task.set_target(mink.SE3(np.concatenate((wxyz, target.position))))
        tq = target.orientation
        best = (math.inf, start.copy(), math.inf, math.inf)
        stall = 0
        iters = 0
        for iters in range(1, max_iterations + 1):
            perr, rerr = _residual(data, bid, target.position, tq)
            score = perr / ptol + (0.0 if position_only else rerr / rtol)
            q_now = data.qpos[kin._qadr].copy()
            if score < best[0] * (1.0 - 1e-3):
                stall = 0
            else:
                stall += 1
            if score < best[0]:
                best = (score, q_now, perr, rerr)
            if perr <= ptol and (position_only or rerr <= rtol):
                return q_now, perr, rerr, iters - 1
            if stall >= 15:  # a local minimum (or the target is out of reach)
                break
            yield
            if position_only:
                # mink's frame error is the SE(3) log, whose translation part mixes in the rotation
                # error: aim at the current orientation so the error is the position error alone
                task.set_target(mink.SE3(np.concatenate((data.xquat[bid], target.position))))
            vel = mink.solve_ik(conf, [task], 1.0, "daqp", damping=1e-8, limits=self.limits,
                                constraints=self.constraints)
            conf.integrate_inplace(vel, 1.0)
            # the QP meets limits and couplings to solver precision: restore them exactly
            kin._qpos(np.clip(data.qpos[kin._qadr], kin.lower, kin.upper), self._qpos)
            conf.update(self._qpos)
        perr, rerr = _residual(data, bid, target.position, tq)
        score = perr / ptol + (0.0 if position_only else rerr / rtol)
        if score < best[0]:
            best = (score, data.qpos[kin._qadr].copy(), perr, rerr)
        return best[1], best[2], best[3], iters


def _residual(data: mujoco.MjData, bid: int, position: FloatArray, quat_xyzw: FloatArray) -> tuple[float, float]:
    perr = float(np.linalg.norm(data.xpos[bid] - position))
    cur = wxyz_to_xyzw(data.xquat[bid])
    inv = np.array([-cur[0], -cur[1], -cur[2], cur[3]])
    rerr = float(np.linalg.norm(rotation_vector(quat_multiply(inv, quat_xyzw))))
    return perr, rerr


def search(
    kin: IKModel,
    solver: IKSolver | None,
    link: str,
    pose: Pose | npt.ArrayLike,
    seed: Positions | None,
    position_only: bool,
    position_tolerance: float,
    orientation_tolerance: float,
    max_iterations: int,
    restarts: int,
    random_seed: int,
) -> Generator[None, None, IKResult]:
    """The IK search of :meth:`Kinematics.ik`: from ``seed``, then random restarts (yields between steps)."""
    bid = kin.body_id(link)
    if bid == 0 or link == kin.root_link:
        raise InvalidValueError(f"ik: {link!r} is the root frame; it does not move")
    target, position_only = ik_target(pose, position_only)
    for what, tol in (("position_tolerance", position_tolerance), ("orientation_tolerance", orientation_tolerance)):
        if not (isinstance(tol, int | float) and tol > 0 and math.isfinite(tol)):
            raise InvalidValueError(f"ik: {what} must be a finite number > 0, got {tol!r}")
    if int(max_iterations) < 1 or int(restarts) < 0:
        raise InvalidValueError("ik: max_iterations must be >= 1 and restarts >= 0")
    q0 = np.clip(kin.resolve(seed, "seed"), kin.lower, kin.upper)
    rng = np.random.default_rng(random_seed)
    best: tuple[float, FloatArray, float, float] | None = None
    total = 0
    if solver is None:
        solver = kin._solver()
    for attempt in range(int(restarts) + 1):
        start = q0 if attempt == 0 else _random_configuration(kin, rng)
        q, perr, rerr, iters = yield from solver.solve(
            bid, link, target, start, position_only, position_tolerance, orientation_tolerance,
            int(max_iterations),
        )
        total += iters
        score = perr / position_tolerance + (0.0 if position_only else rerr / orientation_tolerance)
        if best is None or score < best[0]:
            best = (score, q, perr, rerr)
        if perr <= position_tolerance and (position_only or rerr <= orientation_tolerance):
            q = _tidy(kin, q, q0)
            return IKResult(dict(zip(kin.joint_names, q.tolist(), strict=True)), ok=True,
                            position_error=perr, orientation_error=0.0 if position_only else rerr,
                            iterations=total, attempts=attempt + 1)
    assert best is not None
    _, q, perr, rerr = best
    what = "position" if position_only else "pose"
    rot = "" if position_only else f", {rerr:.4g} rad orientation (tolerance {orientation_tolerance:g} rad)"
    msg = (
        f"IK found no joint positions within the limits of {kin.name!r} that put link {link!r} at the target "
        f"{what}: residual {perr:.4g} m position (tolerance {position_tolerance:g} m){rot} "
        f"after {int(restarts) + 1} attempts ({total} iterations); the target may be out of reach"
    )
    result = IKResult(dict(zip(kin.joint_names, q.tolist(), strict=True)), ok=False, position_error=perr,
                      orientation_error=0.0 if position_only else rerr, iterations=total,
                      attempts=int(restarts) + 1, message=msg)
    raise UnreachablePoseError(msg, result)


def _random_configuration(kin: IKModel, rng: np.random.Generator) -> FloatArray:
    lo = np.where(np.isfinite(kin.lower), kin.lower, -math.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper, math.pi)
    return rng.uniform(lo, hi)


def _tidy(kin: IKModel, q: FloatArray, seed: FloatArray) -> FloatArray:
    """Clip into the limits (QP round-off) and bring continuous joints within pi of the seed."""
    q = np.clip(q, kin.lower, kin.upper)
    cont = ~(np.isfinite(kin.lower) | np.isfinite(kin.upper))
    for k in np.flatnonzero(cont).tolist():
        if kin.joints[k].type != "prismatic":
            q[k] = seed[k] + (q[k] - seed[k] + math.pi) % (2 * math.pi) - math.pi
    return q
