"""Fixed-rate feedback agents: read the state, compute a command, send it, every period.

The pattern of a hand-written control loop, done once and measured::

    class Track(FeedbackAgent):
        rate = 500.0                                   # Hz (default of run_feedback)

        async def setup(self, robot):                  # optional, before the first period
            self.t0 = robot.clock.now()

        async def update(self, state: JointState) -> JointCommand | None:
            target = 0.5 * math.sin(2 * math.pi * (state.stamp - self.t0))
            return JointCommand("position", {"joint1": target})

    stats = await run_feedback(robot, Track(), duration=5.0)   # or: await Track().run(robot, duration=5.0)
    print(stats.summary())

Every period the loop

1. waits on ``robot.clock.sleep_until(deadline)`` for an *absolute* deadline
   ``start + k * period``, ``start`` being when ``setup`` returned (no drift:
   lateness in one period does not shift the next ones;
   :class:`~agentsdk.clock.RealtimeClock` sleeps, then spins the last ~1.5 ms);
2. reads the state (``await robot.read()``), awaits ``agent.update(state)``;
3. sends the returned command through ``robot.command`` -- the normal path, so
   the safety layer limits it and the command watchdog is fed -- or nothing for
   ``None``.

When the loop is late it never bursts to catch up: like the control loop, it runs
the most recent due period at once and skips the older ones, counting them in
:attr:`LoopStats.missed_deadlines`. An ``update`` that takes longer than the
period counts as an overrun. Timing statistics (:class:`LoopStats`) come from the
actual wake-up times on the robot clock and are returned by :func:`run_feedback`
(and kept as ``agent.stats``), also when the loop ends with an exception.

Time models. In realtime the loop runs at ``rate`` Hz of wall time, any rate
(the measured state is refreshed once per control tick, so above the control
rate some periods see the same state again). In
lockstep the same agent runs deterministically in simulated time: wake-ups happen
on control ticks, so the period must be a whole multiple of the control period
(``rate`` must divide the robot's update rate); any other rate raises
:class:`~agentsdk.errors.ConfigurationError` instead of silently running at a
different rate. In lockstep the period errors are exactly zero.

Link poses. ``links=("tool0",)`` (or the agent's ``links`` class attribute) hands
``update`` a :class:`FeedbackState` instead of the plain :class:`JointState`: the same
state plus ``poses``, ``{link: Pose}`` of the chosen links at that state, computed
host-side by ``robot.kinematics`` (one forward-kinematics pass per link; the other links
are not computed). An unknown link raises :class:`~agentsdk.errors.UnknownLinkError`
before ``setup`` runs::

    async def update(state: FeedbackState) -> JointCommand | None:
        z = state.poses["tool0"].position[2]
        ...

    await run_feedback(robot, update, 100.0, links=("tool0",), duration=2.0)

Ending. ``duration`` (robot seconds; the call returns after that long),
``stop`` (an :class:`asyncio.Event`; a sleeping loop is woken at once), an
exception in ``update``/``command`` (propagates), or cancelling the awaiting task.
Then, unless ``hold_on_exit=False``, joints the agent left streaming (velocity or
effort mode, or position with velocity/effort feed-forward) are commanded to hold
their measured position -- what the command watchdog would do after
``command_timeout``, but at once -- and ``agent.teardown(robot)`` is awaited.
Position targets without feed-forward hold by themselves and are left as they are.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import math
from abc import ABC, abstractmethod
from array import array
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np

from .backend import ModeCode
from .errors import AgentSDKError, ConfigurationError, InvalidValueError, RobotClosedError
from .types import JointCommand, JointState

if TYPE_CHECKING:
    from .kinematics import Kinematics
    from .pose import Pose
    from .robot import Robot
    from .sensors import SensorReading

__all__ = ["FeedbackAgent", "FeedbackState", "LoopStats", "UpdateFn", "run_feedback"]

log = logging.getLogger("agentsdk.feedback")

_POS = ModeCode.POSITION

#: a plain ``[async] def update(state) -> JointCommand | None`` accepted by run_feedback
UpdateFn = Callable[[JointState], Awaitable[JointCommand | None] | JointCommand | None]

EndReason = Literal["duration", "stop", "error", "cancelled"]


# --------------------------------------------------------------------------- the per-period input


@dataclass(frozen=True, slots=True)
class FeedbackState(JointState):
    """The measured state handed to ``update`` when link poses were asked for (``links=``).

    A :class:`~agentsdk.types.JointState` (same arrays, same ``stamp``) plus ``poses``:
    ``{link: Pose}`` of the chosen links in the root frame at exactly this state, as
    ``robot.kinematics.fk(link, state)`` gives them.
    """

    #: ``{link: Pose}`` of the chosen links (read-only mapping)
    poses: Mapping[str, Pose]
    #: ``{sensor: reading}`` of the chosen sensors (``sensors=``), shaped like their ROS messages
    sensors: Mapping[str, SensorReading] = field(default_factory=lambda: MappingProxyType({}))


def _pose_links(robot: Robot, links: Sequence[str] | str) -> tuple[tuple[str, ...], Kinematics | None]:
    """The chosen links as a tuple, checked against the robot's kinematics (None when no links)."""
    if isinstance(links, str):
        names: tuple[str, ...] = (links,)
    else:
        try:
            names = tuple(links)
        except TypeError:
            raise InvalidValueError(
                f"links must be a link name or a sequence of link names, got {links!r}"
            ) from None
    if not names:
        return (), None
    for link in names:
        if not isinstance(link, str):
            raise InvalidValueError(f"links must be link names (str), got {link!r}")
    kin = robot.kinematics
    for link in names:
        kin.body_id(link)  # UnknownLinkError naming the link and the valid ones
    return names, kin


def _with_poses(state: JointState, links: tuple[str, ...], kin: Kinematics) -> FeedbackState:
    poses = MappingProxyType({link: kin.fk(link, state) for link in links})
    return FeedbackState(state.names, state.position, state.velocity, state.effort, state.stamp, poses)


# --------------------------------------------------------------------------- statistics


@dataclass(frozen=True, slots=True)
class LoopStats:
    """Timing of one feedback-loop run, in seconds of robot time.

    ``period_error_*`` are statistics of ``|actual period - scheduled period|``
    over consecutive wake-ups (the scheduled period is ``period``, or a multiple
    of it across skipped deadlines); ``latency_*`` of ``wake time - deadline``
    (how late each period started). Percentiles cover the last ``max_samples``
    periods; count, mean and max cover the whole run. With fewer than two
    periods the period-error fields are 0.
    """

    #: requested rate (Hz) and period (s)
    rate: float
    period: float
    #: True when measured on the wall clock (RealtimeClock), False in lockstep
    realtime: bool
    #: number of periods run (calls to update)
    count: int
    #: robot time from the start of the loop to its end (s)
    duration: float
    period_error_mean: float
    period_error_p50: float
    period_error_p99: float
    period_error_max: float
    latency_mean: float
    latency_p50: float
    latency_p99: float
    latency_max: float
    #: deadlines skipped because the loop was more than a period late
    missed_deadlines: int
    #: periods whose update() took longer than the period
    overruns: int
    #: time spent in update() per period
    update_time_mean: float
    update_time_max: float
    #: how the loop ended: "duration", "stop", "error" or "cancelled"
    end_reason: str = "duration"

    @property
    def achieved_rate(self) -> float:
        """Periods run per second of robot time."""
        return self.count / self.duration if self.duration > 0 else 0.0

    def as_dict(self) -> dict[str, Any]:
        """A JSON-serializable dict (plus ``achieved_rate``)."""
        d = asdict(self)
        d["achieved_rate"] = self.achieved_rate
        return d

    def summary(self) -> str:
        """One human-readable line (errors in microseconds)."""
        us = 1e6
        return (
            f"{self.count} periods at {self.rate:g} Hz ({'realtime' if self.realtime else 'lockstep'}, "
            f"{self.duration:.3f} s): period error p50 {self.period_error_p50 * us:.1f} us, "
            f"p99 {self.period_error_p99 * us:.1f} us, max {self.period_error_max * us:.1f} us; "
            f"latency p99 {self.latency_p99 * us:.1f} us; missed deadlines {self.missed_deadlines}, "
            f"overruns {self.overruns}"
        )

    def __str__(self) -> str:
        return self.summary()

    @classmethod
    def from_wake_times(
        cls,
        wakes: Any,
        period: float,
        *,
        deadlines: Any = None,
        realtime: bool = True,
        missed_deadlines: int = 0,
        update_times: Any = None,
        duration: float | None = None,
        end_reason: str = "duration",
    ) -> LoopStats:
        """Statistics of a loop from its wake-up times (e.g. of a baseline loop measured the same way).

        ``deadlines`` default to ``wakes[0] + k * period`` spacing between
        consecutive wakes (i.e. every period is scheduled as one ``period``).
        """
        rec = _Recorder(period, max(1, len(wakes)))
        w = np.asarray(wakes, dtype=float)
        if deadlines is None:
            scheduled = np.full(max(0, len(w) - 1), period)
            lat = np.zeros(len(w))
        else:
            d = np.asarray(deadlines, dtype=float)
            scheduled = np.diff(d)
            lat = w - d
        ups = np.zeros(len(w)) if update_times is None else np.asarray(update_times, dtype=float)
        for i in range(len(w)):
            rec.count += 1
            rec.latency.add(float(lat[i]))
            rec.update_sum += float(ups[i])
            rec.update_max = max(rec.update_max, float(ups[i]))
            if ups[i] > period:
                rec.overruns += 1
            if i:
                rec.period_error.add(abs(float(w[i] - w[i - 1] - scheduled[i - 1])))
        rec.missed = missed_deadlines
        dur = float(w[-1] - w[0]) if duration is None and len(w) else (duration or 0.0)
        return rec.stats(realtime=realtime, duration=dur, end_reason=end_reason)


class _Series:
    """Count, sum and max of a sample series, plus the last ``cap`` samples for percentiles."""

    __slots__ = ("buf", "cap", "max", "n", "pos", "sum")

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self.buf = array("d")
        self.pos = 0
        self.n = 0
        self.sum = 0.0
        self.max = 0.0

    def add(self, x: float) -> None:
        self.n += 1
        self.sum += x
        if x > self.max:
            self.max = x
        if len(self.buf) < self.cap:
            self.buf.append(x)
        else:  # ring buffer: percentiles of the most recent samples
            self.buf[self.pos] = x
            self.pos = (self.pos + 1) % self.cap

    def mean(self) -> float:
        return self.sum / self.n if self.n else 0.0

    def percentiles(self) -> tuple[float, float]:
        if not self.buf:
            return 0.0, 0.0
        p50, p99 = np.percentile(np.frombuffer(self.buf, dtype=float), [50.0, 99.0])
        return float(p50), float(p99)


class _Recorder:
    def __init__(self, period: float, max_samples: int) -> None:
        self.period = period
        self.period_error = _Series(max_samples)
        self.latency = _Series(max_samples)
        self.count = 0
        self.missed = 0
        self.overruns = 0
        self.update_sum = 0.0
        self.update_max = 0.0
        self._last_wake: float | None = None
        self._last_deadline = 0.0

    def add(self, deadline: float, wake: float, update_time: float) -> None:
        self.count += 1
        # clamp: the realtime clock never wakes early; tiny negatives are float noise
        self.latency.add(max(0.0, wake - deadline))
        if self._last_wake is not None:
            self.period_error.add(abs((wake - self._last_wake) - (deadline - self._last_deadline)))
        self._last_wake, self._last_deadline = wake, deadline
        self.update_sum += update_time
        if update_time > self.update_max:
            self.update_max = update_time
        if update_time > self.period:
            self.overruns += 1

    def stats(self, *, realtime: bool, duration: float, end_reason: str) -> LoopStats:
        pe50, pe99 = self.period_error.percentiles()
        la50, la99 = self.latency.percentiles()
        return LoopStats(
            rate=1.0 / self.period,
            period=self.period,
            realtime=realtime,
            count=self.count,
            duration=duration,
            period_error_mean=self.period_error.mean(),
            period_error_p50=pe50,
            period_error_p99=pe99,
            period_error_max=self.period_error.max,
            latency_mean=self.latency.mean(),
            latency_p50=la50,
            latency_p99=la99,
            latency_max=self.latency.max,
            missed_deadlines=self.missed,
            overruns=self.overruns,
            update_time_mean=self.update_sum / self.count if self.count else 0.0,
            update_time_max=self.update_max,
            end_reason=end_reason,
        )


# --------------------------------------------------------------------------- the agent


class FeedbackAgent(ABC):
    """Base class of fixed-rate feedback agents; implement :meth:`update`.

    ``rate`` (Hz) is the default rate of :func:`run_feedback` and ``links`` its default
    ``links`` (link poses carried by the state, see :class:`FeedbackState`). After a run,
    :attr:`stats` holds its :class:`LoopStats`.
    """

    rate: ClassVar[float] = 500.0
    #: links whose poses ``update`` receives (a :class:`FeedbackState`); default of ``run_feedback(links=)``
    links: ClassVar[tuple[str, ...]] = ()
    #: sensors whose latest readings every period's state carries (``FeedbackState.sensors``)
    sensors: ClassVar[tuple[str, ...]] = ()
    stats: LoopStats | None = None

    async def setup(self, robot: Robot) -> None:  # noqa: B027 - optional hook
        """Called once before the first period (not timed)."""

    @abstractmethod
    async def update(self, state: JointState) -> JointCommand | None:
        """Called once per period with the latest measured state; return a command or ``None``.

        Keep it shorter than the period: a longer update is an overrun and makes
        the loop skip deadlines.
        """

    async def teardown(self, robot: Robot) -> None:  # noqa: B027 - optional hook
        """Called once after the loop ends (also after an error or cancellation)."""

    async def run(
        self,
        robot: Robot,
        rate: float | None = None,
        *,
        duration: float | None = None,
        stop: asyncio.Event | None = None,
        hold_on_exit: bool = True,
        links: Sequence[str] | str | None = None,
    ) -> LoopStats:
        """Shorthand for ``await run_feedback(robot, self, rate, ...)``."""
        return await run_feedback(
            robot, self, rate, duration=duration, stop=stop, hold_on_exit=hold_on_exit, links=links
        )


class _FunctionAgent(FeedbackAgent):
    def __init__(self, fn: UpdateFn, rate: float | None) -> None:
        self._fn = fn
        if rate is not None:
            self.rate = rate  # type: ignore[misc]

    async def update(self, state: JointState) -> JointCommand | None:
        result = self._fn(state)
        if inspect.isawaitable(result):
            result = await result
        return result


# --------------------------------------------------------------------------- the loop


def _check_rate(robot: Robot, rate: float) -> tuple[float, int]:
    """The period (s) and, in lockstep, the number of control ticks per period (else 0)."""
    try:
        rate = float(rate)
    except (TypeError, ValueError):
        raise InvalidValueError(f"rate must be a number of Hz, got {rate!r}") from None
    if not (math.isfinite(rate) and rate > 0.0):
        raise InvalidValueError(f"rate must be a finite number of Hz > 0, got {rate!r}")
    period = 1.0 / rate
    if not robot.clock.lockstep:
        return period, 0
    cp = robot.control_period
    ratio = period / cp
    ticks = round(ratio)
    if ticks < 1 or abs(ratio - ticks) > 1e-6 * ratio:
        base = 1.0 / cp
        valid = ", ".join(f"{base / k:g}" for k in range(1, 6))
        raise ConfigurationError(
            f"feedback rate {rate:g} Hz: in lockstep the period ({period:g} s) must be a whole multiple of "
            f"the control period ({cp:g} s, {base:g} Hz); use e.g. {valid} Hz"
        )
    return period, ticks


async def _hold_streamed(robot: Robot, commanded: set[int]) -> None:
    """Joints the agent left streaming (velocity/effort, or position with feed-forward) hold where they are."""
    if not commanded or robot.closed:
        return
    sp = robot.setpoint
    st = await robot.read()
    owned = set(robot.motion_joints)  # joints a trajectory took over since are not ours any more
    names = robot.joint_names
    idx = [
        j
        for j in sorted(commanded)
        if sp.enabled[j]
        and names[j] not in owned
        and (sp.mode[j] != _POS or sp.velocity[j] != 0.0 or sp.effort[j] != 0.0)
    ]
    if idx:
        await robot.command(JointCommand("position", {names[j]: float(st.position[j]) for j in idx}))


async def run_feedback(
    robot: Robot,
    agent: FeedbackAgent | UpdateFn,
    rate: float | None = None,
    *,
    duration: float | None = None,
    stop: asyncio.Event | None = None,
    hold_on_exit: bool = True,
    max_samples: int = 1_000_000,
    links: Sequence[str] | str | None = None,
    sensors: Sequence[str] | str | None = None,
) -> LoopStats:
    """Run ``agent`` at ``rate`` Hz (default ``agent.rate``) until ``duration``, ``stop`` or an error.

    ``agent`` is a :class:`FeedbackAgent` or a plain ``update(state)`` function (async or not).
    ``duration`` is in robot seconds; ``None`` runs until ``stop`` is set or the
    task is cancelled. ``links`` (default ``agent.links``) names links whose poses
    every period's state carries: ``update`` then receives a :class:`FeedbackState`.
    ``sensors`` (default ``agent.sensors``) names sensors whose latest readings it carries too
    (``FeedbackState.sensors``; an unknown name raises :class:`~agentsdk.sensors.UnknownSensorError`).
    Returns the :class:`LoopStats` (also set as ``agent.stats``).

    Raises :class:`~agentsdk.errors.InvalidValueError` for a bad rate or duration,
    :class:`~agentsdk.errors.UnknownLinkError` for a link the robot does not have (before
    ``setup``), and :class:`~agentsdk.errors.ConfigurationError` in lockstep when the period is
    not a whole multiple of the control period. Errors from ``update`` and from
    ``robot.command`` (e.g. :class:`~agentsdk.errors.EStopActive`) propagate after
    the exit hold and ``teardown``.
    """
    if not isinstance(agent, FeedbackAgent):
        if not callable(agent):
            raise InvalidValueError(f"agent must be a FeedbackAgent or an update(state) function, got {agent!r}")
        agent = _FunctionAgent(agent, rate)
    if not inspect.iscoroutinefunction(agent.update):
        raise InvalidValueError(f"{type(agent).__name__}.update must be 'async def update(self, state)'")
    period, ticks = _check_rate(robot, agent.rate if rate is None else rate)
    n_end: int | None = None
    if duration is not None:
        duration = float(duration)
        if not (math.isfinite(duration) and duration >= 0.0):
            raise InvalidValueError(f"duration must be a finite number of seconds >= 0, got {duration!r}")
        n_end = max(0, math.ceil(duration / period - 1e-9))
    if max_samples < 1:
        raise InvalidValueError(f"max_samples must be >= 1, got {max_samples!r}")
    if robot.closed:
        raise RobotClosedError(f"robot {robot.name!r} is closed")
    pose_links, kin = _pose_links(robot, agent.links if links is None else links)
    chosen = agent.sensors if sensors is None else sensors
    sensor_names = (chosen,) if isinstance(chosen, str) else tuple(chosen)
    for name in sensor_names:
        robot.sensors[name]  # UnknownSensorError naming it and the robot's sensors

    clock = robot.clock
    realtime = not clock.lockstep
    rec = _Recorder(period, max_samples)
    commanded: set[int] = set()
    end_reason: EndReason = "error"
    task = asyncio.current_task()
    assert task is not None
    sleeping = False
    interrupted = False

    async def _watch_stop(ev: asyncio.Event) -> None:
        nonlocal interrupted
        await ev.wait()
        if sleeping:  # wake the loop now instead of at its next deadline
            interrupted = True
            task.cancel()

    await agent.setup(robot)  # may take robot time (e.g. move to a start pose): the grid starts after it
    start = clock.now()
    if ticks:
        cp = robot.control_period
        start_tick = round(start / cp)

        def deadline_at(k: int) -> float:
            return (start_tick + k * ticks) * cp  # exactly how LockstepClock.now() counts time

    else:

        def deadline_at(k: int) -> float:
            return start + k * period

    watcher = asyncio.get_running_loop().create_task(_watch_stop(stop)) if stop is not None else None
    try:
        index = robot.joint_index
        k = 0
        while True:
            if stop is not None and stop.is_set():
                end_reason = "stop"
                break
            deadline = deadline_at(k)
            if k:
                sleeping = True
                try:
                    await clock.sleep_until(deadline)
                except asyncio.CancelledError:
                    if interrupted and task.uncancel() == 0:
                        end_reason = "stop"
                        break
                    raise
                finally:
                    sleeping = False
            if n_end is not None and k >= n_end:
                end_reason = "duration"
                break
            wake = clock.now()
            state = await robot.read()
            if kin is not None:
                state = _with_poses(state, pose_links, kin)
            if sensor_names:
                poses = state.poses if isinstance(state, FeedbackState) else MappingProxyType({})
                state = FeedbackState(state.names, state.position, state.velocity, state.effort, state.stamp, poses,
                                      robot.sensors.snapshot(sensor_names))
            t_update = clock.now()
            cmd = await agent.update(state)
            update_time = clock.now() - t_update
            if cmd is not None:
                applied = await robot.command(cmd)
                if hold_on_exit:
                    commanded.update(index[n] for n in applied.values)  # always a mapping
            rec.add(deadline, wake, update_time)
            k += 1
            late = clock.now() - deadline_at(k)
            if late > period:
                # skip the deadlines that are long past instead of bursting to catch up
                skipped = math.floor(late / period)
                if n_end is not None:
                    skipped = min(skipped, n_end - k)
                rec.missed += skipped
                k += skipped
    except asyncio.CancelledError:
        end_reason = "cancelled"
        raise
    finally:
        if watcher is not None:
            watcher.cancel()
            await asyncio.gather(watcher, return_exceptions=True)
        agent.stats = rec.stats(realtime=realtime, duration=clock.now() - start, end_reason=end_reason)
        try:
            if hold_on_exit:
                try:
                    await _hold_streamed(robot, commanded)
                except AgentSDKError as exc:  # e-stopped, closed...: the safety layer is in charge
                    log.debug("feedback loop: exit hold skipped: %s", exc)
        finally:
            await agent.teardown(robot)
    return agent.stats
