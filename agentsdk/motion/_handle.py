"""The :class:`Motion` handle a user awaits, cancels and reads feedback from."""

from __future__ import annotations

import asyncio
import dataclasses
import math
from collections.abc import AsyncIterator, Callable, Generator, Sequence
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ..config import format_value
from ..errors import InvalidValueError
from ..loop import ControlLoop
from ..trajectory import (
    Trajectory,
)
from ._types import Feedback, MotionResult, ResultCode, _link_names

if TYPE_CHECKING:
    from ..kinematics import Kinematics


class _MotionOwner(Protocol):
    """What a :class:`Motion` needs from the manager that runs it (implemented by ``MotionManager``)."""

    loop: ControlLoop
    sensors_source: Callable[[], Any] | None

    def kinematics(self) -> Kinematics:
        """The robot's kinematics, for link poses in feedback."""

    def _request_stop(self, motion: Motion, code: ResultCode, msg: str) -> None:
        """Stop ``motion`` along a stop ramp, then resolve it with ``code``."""


class Motion:
    """Handle of a running (or scheduled) trajectory. Awaitable; ``cancel()``; ``feedback()``."""

    def __init__(self, manager: _MotionOwner, idx: np.ndarray, names: tuple[str, ...],
                 trajectory: Trajectory, start_time: float) -> None:
        self._mgr = manager
        self.idx = idx
        self.joint_names = names
        #: the trajectory as executed: points already elapsed at a past ``start_time`` dropped,
        #: continuous joints moved by whole turns, stretched if ``stretch_to_limits`` slowed it
        self.trajectory = trajectory
        #: robot time at which the trajectory starts (``time_from_start`` is relative to it)
        self.start_time = start_time
        self._future: asyncio.Future[MotionResult] = asyncio.get_running_loop().create_future()
        #: the executor's latest tick (references to its buffers; frozen when the motion ends)
        self._snap: _FeedbackSnapshot | None = None
        self._fb: Feedback | None = None
        self._fb_seq = -1
        #: measured positions of every joint at the latest tick, kept only while a feedback
        #: stream with link poses runs (``_pose_streams > 0``)
        self._feedback_q: np.ndarray | None = None
        self._pose_streams = 0
        self._cancel_requested = False

    @property
    def _feedback(self) -> Feedback | None:
        """The latest tick's :class:`Feedback`, built when read (the tick itself allocates nothing)."""
        snap = self._snap
        if snap is None:
            return None
        if self._fb is None or self._fb_seq != snap.seq:
            self._fb = snap.feedback(self.joint_names)
            self._fb_seq = snap.seq
        return self._fb

    # the executor's side: it resolves and publishes only through these ----------
    def _settle(self, result: MotionResult | None) -> None:
        """End with ``result`` (the first result wins; later ones are ignored); freeze the feedback."""
        if self._snap is not None:
            self._snap.freeze()
        if result is not None and not self._future.done():
            self._future.set_result(result)

    def _fail(self, exc: BaseException) -> None:
        """End with the backend's failure ``exc`` (re-raised where the motion is awaited)."""
        if not self._future.done():
            self._future.set_exception(exc)
            self._future.exception()  # mark retrieved: the awaiting side re-raises it

    def _publish(self) -> _FeedbackSnapshot:
        """The snapshot the executor fills each tick (made on the first tick, reused after)."""
        snap = self._snap
        if snap is None:
            snap = self._snap = _FeedbackSnapshot()
            snap.keep_measured = self._pose_streams > 0
        return snap

    def _keep_measured(self, position: np.ndarray) -> None:
        """Keep the measured positions of every joint at this tick.

        The executor calls this while the snapshot's ``keep_measured`` says a feedback stream wants link poses.
        """
        self._feedback_q = position.copy()

    def _count_pose_streams(self, delta: int) -> None:
        """A feedback stream with link poses starts (+1) or ends (-1); the snapshot says whether any runs."""
        self._pose_streams += delta
        keep = self._pose_streams > 0
        if not keep:
            self._feedback_q = None
        if self._snap is not None:
            self._snap.keep_measured = keep

    # awaitable ------------------------------------------------------------
    def __await__(self) -> Generator[Any, None, MotionResult]:
        return self._wait().__await__()

    async def _wait(self) -> MotionResult:
        try:
            return await asyncio.shield(self._future)
        except asyncio.CancelledError:
            # the awaiting task was cancelled (e.g. asyncio.timeout): stop safely
            self.cancel()
            raise

    def done(self) -> bool:
        """True once the motion has ended (its result is available)."""
        return self._future.done()

    def result(self) -> MotionResult:
        """The result; raises ``asyncio.InvalidStateError`` while running."""
        return self._future.result()

    def cancel(self) -> None:
        """Decelerate to rest within the joints' limits, then hold. Result: CANCELED.

        A motion whose scheduled start has not come yet ends at once (nothing moved).
        Idempotent; never raises.
        """
        if self._future.done() or self._cancel_requested:
            return
        self._cancel_requested = True
        self._mgr._request_stop(self, ResultCode.CANCELED, "canceled")

    def stop_early(self, reason: str) -> None:
        """End SUCCESSFUL before the goal (a guarded move's condition held): decelerate within the limits, hold.

        Idempotent; never raises. See :mod:`agentsdk.sensors`.
        """
        if self._future.done() or self._cancel_requested:
            return
        self._cancel_requested = True
        self._mgr._request_stop(self, ResultCode.SUCCESSFUL, reason)

    def feedback(
        self, rate: float = 50.0, *, links: Sequence[str] | str = (), sensors: Sequence[str] | str = ()
    ) -> AsyncIterator[Feedback]:
        """Yield feedback at ``rate`` Hz of robot time until the motion ends (the last one included).

        ``links`` (a link name or a sequence of them, e.g. ``("tool0",)``) adds their poses to
        every message: :attr:`Feedback.poses` at the measured state of the message's ``time``
        and :attr:`Feedback.desired_poses` at the desired positions, computed host-side by
        ``robot.kinematics`` (the same on every backend). Checked here, at the call: a bad
        rate raises :class:`~agentsdk.errors.InvalidValueError`, an unknown link
        :class:`~agentsdk.errors.UnknownLinkError` naming it and listing the robot's links.
        ``sensors`` adds the latest readings of those sensors (:attr:`Feedback.sensors`).
        """
        if not (rate > 0 and math.isfinite(rate)):
            raise InvalidValueError(f"feedback rate must be a positive number of Hz, got {format_value(rate)}")
        names = _link_names(links)
        kin: Kinematics | None = None
        if names:
            kin = self._mgr.kinematics()
            for link in names:
                kin.body_id(link)  # UnknownLinkError naming the link and the valid ones
        stream = self._feedback_stream(1.0 / rate, names, kin)
        chosen = (sensors,) if isinstance(sensors, str) else tuple(sensors)
        if not chosen:
            return stream
        source = self._mgr.sensors_source
        if source is None:
            raise InvalidValueError("this robot has no sensors to add to motion feedback")
        robot_sensors = source()
        for name in chosen:
            robot_sensors[name]  # UnknownSensorError naming it and the robot's sensors
        return _with_sensors(stream, robot_sensors, chosen)

    async def _feedback_stream(
        self, period: float, links: tuple[str, ...], kin: Kinematics | None
    ) -> AsyncIterator[Feedback]:
        clock = self._mgr.loop.clock
        next_t = clock.now()
        last: Feedback | None = None
        if kin is not None:
            self._count_pose_streams(1)  # from now on every tick keeps the full measured state
        try:
            while True:
                fb = self._feedback
                if fb is not None and fb is not last:
                    if kin is None:
                        last = fb
                        yield fb
                    else:
                        q = self._feedback_q
                        if q is not None or self._future.done():
                            last = fb
                            yield self._with_poses(fb, q, links, kin)
                        # else: published before this stream asked for the full state; the next tick's will do
                if self._future.done():
                    return
                next_t += period
                await clock.sleep_until(next_t)
        finally:
            if kin is not None:
                self._count_pose_streams(-1)

    def _with_poses(self, fb: Feedback, q: np.ndarray | None, links: tuple[str, ...], kin: Kinematics) -> Feedback:
        """``fb`` plus the poses of ``links`` at its measured state and at its desired positions."""
        if q is None:
            # the motion ended before a tick kept the full state: its own joints as measured at
            # fb.time, the others (not driven by it) as measured now
            q = self._mgr.loop.snapshot().position.copy()
            q[self.idx] = fb.actual_positions
        qd = q.copy()
        qd[self.idx] = fb.desired_positions
        poses = MappingProxyType({link: kin.fk(link, q) for link in links})
        desired = MappingProxyType({link: kin.fk(link, qd) for link in links})
        return dataclasses.replace(fb, poses=poses, desired_poses=desired)

    def __repr__(self) -> str:
        state = self._future.result().code.name if self._future.done() else "running"
        return f"<Motion {list(self.joint_names)} {state}>"


async def _with_sensors(
    stream: AsyncIterator[Feedback], sensors: Any, names: tuple[str, ...]
) -> AsyncIterator[Feedback]:
    async for fb in stream:
        yield dataclasses.replace(fb, sensors=sensors.snapshot(names))


class _FeedbackSnapshot:
    """What the executor wrote in its last tick for one motion: references to its tick buffers.

    :class:`Feedback` is built from it only when someone reads it; :meth:`freeze` copies the
    arrays when the motion ends (the executor may reuse its buffers for a stop afterwards).
    """

    __slots__ = ("actual_q", "actual_v", "err", "keep_measured", "progress", "q", "seq", "time", "v")

    def __init__(self) -> None:
        #: a feedback stream wants link poses: the executor hands every tick's measured positions to
        #: :meth:`Motion._keep_measured` (set by the motion only)
        self.keep_measured = False
        self.seq = 0
        self.time = 0.0
        self.progress = 0.0
        self.q = self.v = self.actual_q = self.actual_v = self.err = np.zeros(0)

    def freeze(self) -> None:
        self.q, self.v, self.err = self.q.copy(), self.v.copy(), self.err.copy()
        self.actual_q, self.actual_v = self.actual_q.copy(), self.actual_v.copy()

    def feedback(self, names: tuple[str, ...]) -> Feedback:
        return Feedback(self.time, names, self.q.copy(), self.v.copy(), self.actual_q.copy(), self.actual_v.copy(),
                        self.err.copy(), self.progress)
