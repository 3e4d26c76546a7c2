"""Replaying a recording into a backend and measuring the divergence (:func:`replay`, :class:`ReplayResult`)."""

from __future__ import annotations

import asyncio
import json
import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..backend import ModeCode, SetpointView
from ..errors import ConfigurationError
from ..loop import Phase, Setpoint, StateView
from ._channels import NS_PER_S, robot_spec_for_metadata, stamp_ns
from ._reader import RunData
from ._recorder import Recorder

if TYPE_CHECKING:

    from ..robot import Robot


log = logging.getLogger("agentsdk.recording")


# ------------------------------------------------------------------ replay
@dataclass
class ReplayResult:
    """Divergence of the replayed joint positions from the recorded ones (per joint, rad or m).

    .. attribute:: interpolated
       :type: bool

       True for a real-time recording: its stamps are off the tick grid, the replay is interpolated.

    .. attribute:: notes
       :type: list[str]

       Why the replay may not be exact (printed under the table): e.g. a recording without the
       setpoint's acceleration, replayed with an estimate of it.
    """

    names: tuple[str, ...]
    max_abs: dict[str, float]
    rms: dict[str, float]
    samples: int
    ticks: int
    replayed: RunData
    config_changed: bool = False
    # documented in the class docstring (Sphinx reads field comments only from the package __init__)
    interpolated: bool = False
    notes: list[str] = field(default_factory=list)

    @property
    def worst(self) -> float:
        """The largest absolute divergence over all joints."""
        return max(self.max_abs.values(), default=0.0)

    def lines(self) -> list[str]:
        """A table of the divergence per joint, one line per row."""
        width = max([len("joint"), *(len(n) for n in self.names)])
        out = [
            f"divergence of joint positions (replayed - recorded) over {self.samples} samples"
            + (" (real-time recording: replay interpolated, approximate):" if self.interpolated else ":"),
            f"  {'joint':{width}s}  {'max |err|':>11s}  {'RMS':>11s}",
        ]
        for n in self.names:
            out.append(f"  {n:{width}s}  {self.max_abs[n]:11.3e}  {self.rms[n]:11.3e}")
        out.extend(f"note: {note}" for note in self.notes)
        return out


async def replay(
    data: RunData,
    *,
    backend: str | None = None,
    robot: str | None = None,
    options: Mapping[str, Any] | None = None,
    record: str | os.PathLike[str] | None = None,
    on_robot: Callable[[Robot], Any] | None = None,
) -> ReplayResult:
    """Feed the recorded setpoints, tick by tick, into a fresh connection and compare joint states."""
    from ..robot import connect

    if not len(data.state_time):
        raise ConfigurationError("the recording has no joint states to replay")
    backend = backend or data.backend or "mujoco"
    robot = robot or data.robot
    if not robot:
        raise ConfigurationError("the recording does not name its robot; pass --robot")
    opts: dict[str, Any] = {}
    if backend == data.backend and data.metadata.get("backend_options"):
        opts.update(json.loads(data.metadata["backend_options"]))
        opts.pop("gui", None)  # a recording made with --view replays headless
    opts.update(options or {})
    end_ns = int(data.state_time[-1])
    async with connect(backend, robot=robot, safety={"watchdog_modes": ()}, **opts) as bot:
        index = bot.joint_index
        if abs(bot.control_period - data.period) > 1e-12:
            raise ConfigurationError(
                f"control period of {bot.name} on {backend} is {bot.control_period:g} s, "
                f"the recording's is {data.period:g} s; replay needs the same period"
            )
        missing = [n for n in data.names if n not in index]
        if missing:
            raise ConfigurationError(
                f"robot {bot.name!r} has no joint(s) {', '.join(missing)} from the recording "
                f"(its joints: {', '.join(bot.joint_names)})"
            )
        config_changed = False
        recorded_config = data.metadata.get("robot_config")
        if recorded_config:
            config_changed = json.loads(recorded_config) != bot.backend.config.model_dump(mode="json")
            if config_changed:
                log.warning("robot.yaml of %s differs from the recorded one; replay may diverge", bot.name)
        cols = np.array([index[n] for n in data.names], dtype=np.intp)
        # the replay samples the joint states at the recording's rate, so every recorded sample has its twin
        recorded_rate = data.metadata.get("record_rate", "")
        rec = Recorder(
            bot,
            record,
            keep=True,
            rate=float(recorded_rate) if recorded_rate else None,
            metadata={
                "robot": robot_spec_for_metadata(robot),
                "backend_options": json.dumps(opts, sort_keys=True, default=str),
                "behavior": data.metadata.get("behavior", ""),
                "replay_of": data.metadata.get("created", ""),
            },
        )
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        half = stamp_ns(bot.control_period) // 2
        cmd_ns = data.cmd_time
        pos, vel, eff = data.cmd_position, data.cmd_velocity, data.cmd_effort
        kp, kd, en, mode, tgt = data.cmd_kp, data.cmd_kd, data.cmd_enabled, data.cmd_mode, data.cmd_target
        notes: list[str] = []
        acc = data.cmd_acceleration
        if acc is None:
            acc = estimated_acceleration(data)
            notes.append(
                f"the recording ({data.metadata.get('format', '?')}, agentsdk "
                f"{data.metadata.get('agentsdk_version', '?')}) does not carry the setpoint's acceleration, which "
                "the servo law's inverse-dynamics term feeds forward: replayed with an estimate from the recorded "
                "velocity setpoints, so the replay is close but not exact"
            )
            log.warning("%s", notes[-1])

        def update(t: float, st: StateView, sp: Setpoint) -> bool:
            ns = stamp_ns(t)
            if ns >= end_ns - half:
                return False
            i = int(np.searchsorted(cmd_ns, ns, side="right")) - 1
            if i >= 0:
                sp.position[cols] = pos[i]
                sp.velocity[cols] = vel[i]
                sp.acceleration[cols] = acc[i]
                sp.effort[cols] = eff[i]
                sp.kp[cols] = kp[i]
                sp.kd[cols] = kd[i]
                sp.enabled[cols] = en[i]
                sp.mode[cols] = mode[i]
                sp.target[cols] = tgt[i]
            return True

        def watch(t: float, st: StateView, sp: SetpointView) -> None:
            if stamp_ns(t) >= end_ns - half and not done.done():
                feeding.remove()
                done.set_result(None)

        def fault(exc: BaseException) -> None:
            if not done.done():
                done.set_exception(exc)

        bot.add_tick_hook(Phase.OBSERVE, watch)
        bot.add_fault_listener(fault)
        if on_robot is not None:
            on_robot(bot)
        feeding = bot.add_tick_hook(Phase.COMMAND, update)
        try:
            await done
        except BaseException:
            feeding.remove()
            await bot.close()
            rec.finish()
            raise
        ticks = bot.ticks
    rec.finish()  # after close: joining the writer must not stall the control loop
    result = _compare(data, rec.data(), ticks, config_changed)
    result.notes.extend(notes)
    return result


def estimated_acceleration(data: RunData) -> np.ndarray:
    """The setpoint acceleration of every command row, estimated for a recording that does not carry it.

    Central differences of the recorded velocity setpoints where a row and both neighbours are
    commands of consecutive ticks (a moving trajectory writes a row every tick; inside one of its
    jerk-limited segments the velocity is quadratic in time, so the difference is its derivative),
    on enabled position-mode joints (the only ones the trajectory executor feeds an acceleration
    to); 0 elsewhere (holds, velocity and effort modes, the ends of a motion's rows).
    """
    vel, t = data.cmd_velocity, data.cmd_time
    out = np.zeros_like(vel)
    if len(t) < 3:
        return out
    tick = round(data.period * NS_PER_S)
    dt = np.diff(t)
    inner = (np.abs(dt[:-1] - tick) <= 1) & (np.abs(dt[1:] - tick) <= 1)  # rows 1 .. n-2
    span = (t[2:] - t[:-2]).astype(np.float64) / NS_PER_S
    with np.errstate(invalid="ignore", divide="ignore"):
        central = (vel[2:] - vel[:-2]) / span[:, None]
    servo = (data.cmd_mode[1:-1] == ModeCode.POSITION) & data.cmd_enabled[1:-1] & inner[:, None]
    out[1:-1] = np.where(servo & np.isfinite(central), central, 0.0)
    return out


def _compare(data: RunData, replayed: RunData, ticks: int, config_changed: bool) -> ReplayResult:
    cols = [replayed.names.index(n) for n in data.names]
    rt = replayed.state_time
    if not len(rt):
        raise ConfigurationError("the replay produced no joint states")
    rows = np.minimum(np.searchsorted(rt, data.state_time), len(rt) - 1)
    if np.array_equal(rt[rows], data.state_time):
        actual = replayed.position[rows][:, cols]
        interpolated = False
    elif data.metadata.get("realtime") == "true":
        # real-time stamps are off the tick grid: compare against the replay interpolated in time
        actual = np.column_stack([np.interp(data.state_time, rt, replayed.position[:, c]) for c in cols])
        interpolated = True
    else:
        first = int(data.state_time[np.argmax(rt[rows] != data.state_time)]) / NS_PER_S
        raise ConfigurationError(f"the replay has no joint state at t={first:.6f} s")
    diff = actual - data.position
    max_abs = {n: float(np.max(np.abs(diff[:, j]))) for j, n in enumerate(data.names)}
    rms = {n: float(np.sqrt(np.mean(diff[:, j] ** 2))) for j, n in enumerate(data.names)}
    return ReplayResult(data.names, max_abs, rms, len(data.state_time), ticks, replayed, config_changed, interpolated)
