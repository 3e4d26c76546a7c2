"""Jogging: small, bounded moves of the end effector (Cartesian) or of one joint, shared by every jog input.

The web page's keys and buttons (:mod:`agentsdk.webview`), the terminal keyboard (:mod:`agentsdk.keyjog`)
and a gamepad (:mod:`agentsdk.gamepad`) all drive a :class:`Jogger`:

* **Cartesian**: the end effector (:func:`agentsdk.arm.end_effector`) moves along a root-frame vector in a
  straight line (``move_to_pose(..., linear=True)``) from its *desired* pose, so steps add up exactly; arms
  with fewer than 6 joints in the chain jog the position only.
* **Joint**: one joint moves by a step from its desired position, clipped into its limits.
* **One step at a time** (:meth:`Jogger.submit`): a request while a step runs is dropped, never queued, so
  nothing moves after the input stops (a held key's auto-repeat does not pile up steps).
* **Release = hold** (:meth:`Jogger.release`): the running step is cancelled; the motion decelerates to rest
  within the joints' limits and the robot holds there.

Every step goes through ``move_to_pose``/``move_to``, so the safety layer's limits apply; a refused step
(out of reach, e-stop latched) comes back as a :class:`agentsdk.MotionResult` that is not ``ok``.

The keys (the same in the page and in the terminal; none of them moves the page's camera, which uses
W/A/S/D/Q/E and the arrows):

======================  ===========================================
``I`` / ``K``           +x / -x (root frame)
``J`` / ``L``           +y / -y
``U`` / ``O``           +z / -z
``1`` … ``9``           joint 1…9 forwards
Shift+``1`` … ``9``     joint 1…9 backwards (``!@#$%^&*(`` in a terminal)
======================  ===========================================
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, TextIO

import numpy as np
import numpy.typing as npt

from .errors import InvalidValueError

if TYPE_CHECKING:
    from .motion import MotionResult
    from .robot import Robot

__all__ = [
    "CARTESIAN_KEYS", "JOG_STEP", "JOINT_STEP", "SHIFTED_DIGITS", "JogAction", "Jogger", "StepReport", "key_action",
]

#: one Cartesian jog step (m) and one joint jog step (rad, or m for a prismatic joint)
JOG_STEP = 0.01
JOINT_STEP = 0.05

#: key -> (root-frame axis, direction)
CARTESIAN_KEYS: dict[str, tuple[int, float]] = {
    "i": (0, 1.0), "k": (0, -1.0), "j": (1, 1.0), "l": (1, -1.0), "u": (2, 1.0), "o": (2, -1.0),
}
#: what Shift+1..9 types on a US keyboard (a terminal sees the character, not the key)
SHIFTED_DIGITS = "!@#$%^&*("


@dataclass(frozen=True)
class JogAction:
    """One jog request: ``kind`` "cartesian" (``axis`` 0, 1, 2) or "joint" (``axis`` = joint index)."""

    kind: Literal["cartesian", "joint"]
    axis: int
    sign: float

    def describe(self, joint_names: tuple[str, ...] | list[str]) -> str:
        """``+x`` or ``joint2 -`` (for messages)."""
        sign = "+" if self.sign > 0 else "-"
        if self.kind == "cartesian":
            return f"{sign}{'xyz'[self.axis]}"
        return f"{joint_names[self.axis]} {sign}"


def key_action(key: str, n_joints: int, *, shift: bool = False) -> JogAction | None:
    """The jog a key stands for (see the module table), or None for any other key.

    ``key`` is one character as typed (a terminal: ``"!"`` is Shift+1) or a key name with ``shift``.
    """
    if len(key) != 1:
        return None
    low = key.lower()
    if low in CARTESIAN_KEYS:
        axis, sign = CARTESIAN_KEYS[low]
        return JogAction("cartesian", axis, sign)
    if key in SHIFTED_DIGITS:
        index, sign = SHIFTED_DIGITS.index(key), -1.0
    elif key.isdigit() and key != "0":
        index, sign = int(key) - 1, (-1.0 if shift else 1.0)
    else:
        return None
    if index >= n_joints:
        return None
    return JogAction("joint", index, sign)


class Jogger:
    """Jogs one robot (see the module documentation). Use it from the robot's event loop."""

    def __init__(self, robot: Robot, link: str | None = None, *, step: float = JOG_STEP,
                 joint_step: float = JOINT_STEP) -> None:
        from .arm import end_effector

        if not (np.isfinite(step) and step > 0 and np.isfinite(joint_step) and joint_step > 0):
            raise InvalidValueError(f"jog steps must be positive, got {step!r} m and {joint_step!r} rad")
        self.robot = robot
        self.link = link if link is not None else end_effector(robot.kinematics)
        if self.link not in robot.link_names:
            raise InvalidValueError(f"unknown link {self.link!r}; links: {', '.join(robot.link_names)}")
        self.step = float(step)
        self.joint_step = float(joint_step)
        self._full = len(robot.kinematics.chain(self.link)) >= 6
        self._task: asyncio.Task[MotionResult] | None = None

    @property
    def busy(self) -> bool:
        """True while a step runs."""
        return self._task is not None and not self._task.done()

    async def cartesian(self, delta: npt.ArrayLike) -> MotionResult:
        """Move the end effector by ``delta`` (3,) metres in the root frame, in a straight line."""
        from .pose import Pose

        d = np.asarray(delta, dtype=float).reshape(3)
        if not np.all(np.isfinite(d)):
            raise InvalidValueError(f"a jog needs a finite displacement, got {d.tolist()}")
        robot = self.robot
        kin = robot.kinematics
        pose = kin.fk(self.link, robot.desired_state()[0])
        return await robot.move_to_pose(self.link, Pose(pose.position + d, pose.orientation), linear=True,
                                        position_only=not self._full)

    async def joint(self, index: int, step: float) -> MotionResult:
        """Move joint ``index`` by ``step`` from its desired position, clipped into its limits."""
        robot = self.robot
        if not 0 <= index < len(robot.joints):
            raise InvalidValueError(f"no joint {index + 1}: {robot.name} has {len(robot.joints)} joints")
        j = robot.joints[index]
        target = min(max(float(robot.desired_state()[0][index]) + step, j.lower), j.upper)
        return await robot.move_to({j.name: target})

    def run(self, action: JogAction, scale: float = 1.0) -> Coroutine[Any, Any, MotionResult]:
        """The step ``action`` stands for (``scale`` times one step), as a coroutine to submit."""
        if action.kind == "cartesian":
            delta = np.zeros(3)
            delta[action.axis] = action.sign * self.step * scale
            return self.cartesian(delta)
        return self.joint(action.axis, action.sign * self.joint_step * scale)

    def submit(self, make: Callable[[], Coroutine[Any, Any, MotionResult]],
               done: Callable[[MotionResult | BaseException], None] | None = None) -> asyncio.Task[MotionResult] | None:
        """Start the step ``make()`` unless one runs (then drop it and return None).

        ``done`` gets the step's result (or the exception that ended it; not on cancellation).
        """
        if self.busy:
            return None
        task = asyncio.get_running_loop().create_task(make(), name="agentsdk-jog")
        self._task = task
        if done is not None:

            def _report(t: asyncio.Task[MotionResult]) -> None:
                if t.cancelled():
                    return
                exc = t.exception()
                done(exc if exc is not None else t.result())

            task.add_done_callback(_report)
        return task

    def release(self) -> None:
        """Release = hold: cancel the running step; the robot decelerates to rest and holds."""
        if self._task is not None and not self._task.done():
            self._task.cancel()

    async def wait(self) -> None:
        """Wait for the running step (if any) to end, however it ends."""
        task = self._task
        if task is not None and not task.done():
            await asyncio.wait([task])
        if task is not None and task.done() and not task.cancelled():
            task.exception()  # retrieved: whoever submitted it got it through ``done``

    async def aclose(self) -> None:
        """Release (the robot holds) and wait until the step has stopped."""
        self.release()
        await self.wait()


class StepReport:
    """The ``done`` callback of a console jog (:meth:`Jogger.submit`): counts the steps done, prints why one was not.

    ``after_step`` (optional) gives a line printed after each step done (the keyboard prints where the
    end effector is).
    """

    def __init__(self, out: TextIO, after_step: Callable[[], str] | None = None) -> None:
        self.out = out
        self.after_step = after_step
        #: steps that ended SUCCESSFUL
        self.steps = 0

    def __call__(self, result: MotionResult | BaseException) -> None:
        """Take the outcome of one step."""
        if isinstance(result, BaseException):
            print(f"jog failed: {result}", file=self.out, flush=True)
        elif result.ok:
            self.steps += 1
            if self.after_step is not None:
                print(self.after_step(), file=self.out, flush=True)
        else:
            print(f"jog refused: {result.message}", file=self.out, flush=True)
