"""The lockstep tick, hashed: performance work on the tick path must not change a single bit.

Each scenario (hold, follow, cancel, e-stop, speed scaling, push, goal tolerance, preemption by
a scheduled motion, feedback) runs arm3 and humanoid in lockstep on MuJoCo and PyBullet and
hashes, every tick, the robot time, the whole setpoint (every float row, ``enabled``, ``mode``)
and the measured state, plus the motions' results, the feedback messages a stream received and
the safety events. The hashes are compared with ``tests/data/tick_hashes.json``, recorded with
the code before an optimisation: a refactor of the executor, the sampler, the safety filter or
a backend's step path that passes this test computes exactly what it computed before.

The reference depends on the simulators' and numpy's builds, so it is keyed by their
versions and the machine; elsewhere the test skips (say so rather than compare apples and
oranges). A change that is *meant* to change the physics or the setpoints (a new servo law
term, a new default) rewrites the reference on purpose::

    AGENTSDK_UPDATE_TICK_HASHES=1 python -m pytest tests/test_tick_hashes.py
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import JointCommand, Phase, Tolerances, Trajectory, TrajectoryPoint
from agentsdk.errors import BackendUnavailableError
from agentsdk.registry import load_backend

REFERENCE = Path(__file__).parent / "data" / "tick_hashes.json"
UPDATE = os.environ.get("AGENTSDK_UPDATE_TICK_HASHES") == "1"
SCENARIOS = ("hold", "follow", "cancel", "estop", "speed", "push", "goal", "preempt", "feedback", "awaited")
BACKENDS = ("mujoco", "pybullet")
ROBOTS = ("arm3", "humanoid")


def _fingerprint(backend: str) -> str:
    """The builds a hash depends on: the simulator, numpy, Python, the architecture and the CPU model."""
    if backend == "mujoco":
        import mujoco

        sim = f"mujoco {mujoco.__version__}"
    else:
        import pybullet

        sim = f"pybullet api {pybullet.getAPIVersion()}"
    return f"{sim}; numpy {np.__version__}; python {platform.python_version()}; {platform.machine()}; {_cpu()}"


def _cpu() -> str:
    """The CPU model and its instruction sets: numpy's BLAS and MuJoCo pick their SIMD kernels at run time."""
    model, flags = platform.processor() or "unknown cpu", ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:  # the instruction sets the kernels are chosen by
                flags = hashlib.sha256(" ".join(sorted(line.split(":", 1)[1].split())).encode()).hexdigest()[:12]
    except OSError:
        pass
    return f"{model} (flags {flags or '?'})"


class _Hasher:
    """sha256 over every tick's time, setpoint and measured state (an OBSERVE hook that runs last)."""

    def __init__(self, robot: agentsdk.Robot) -> None:
        self.h = hashlib.sha256()
        self.ticks = 0
        robot.add_tick_hook(Phase.OBSERVE, self._tick, order=1 << 30)

    def _tick(self, t: float, st: Any, sp: Any) -> None:
        h = self.h
        h.update(np.float64(t).tobytes())
        for a in (sp.position, sp.velocity, sp.effort, sp.kp, sp.kd, sp.target, sp.acceleration, sp.enabled,
                  sp.mode, st.position, st.velocity, st.effort):
            h.update(np.ascontiguousarray(a).tobytes())
        self.ticks += 1

    def add(self, *items: Any) -> None:
        self.h.update(repr(items).encode())


def _goal(robot: agentsdk.Robot, frac: float) -> list[float]:
    """A position ``frac`` of the way through every joint's range (the middle of unbounded ones)."""
    out = []
    for j in robot.joints:
        lo = j.lower if np.isfinite(j.lower) else -1.0
        hi = j.upper if np.isfinite(j.upper) else 1.0
        out.append(lo + (hi - lo) * frac)
    return out


def _result(m: Any) -> tuple[Any, ...]:
    r = m.result()
    return (r.code.name, r.message, r.time, sorted(r.error.items()))


async def _scenario(backend: str, robot_name: str, what: str) -> tuple[str, int]:
    async with agentsdk.connect(backend, robot=robot_name, safety={"stall_timeout": 30.0}) as robot:
        hasher = _Hasher(robot)
        names = list(robot.joint_names)
        clock = robot.clock
        start = (await robot.read()).position.tolist()
        plan = Trajectory(names, [TrajectoryPoint(0.6, _goal(robot, 0.6)), TrajectoryPoint(1.1, _goal(robot, 0.4))])
        if what == "hold":
            await robot.command(JointCommand("position", start))
            await clock.sleep(0.4)
        elif what == "follow":
            # a planned (jerk-limited, many-segment) move, then a hand-written trajectory to its end
            hasher.add(_result_of(await robot.move_to(dict(zip(names, _goal(robot, 0.55), strict=True)))))
            m = robot.follow(plan, stretch_to_limits=True)
            await m
            hasher.add(_result(m))
            await clock.sleep(0.05)
        elif what == "cancel":
            m = robot.follow(plan, stretch_to_limits=True)
            await clock.sleep(0.35)
            m.cancel()
            await m
            hasher.add(_result(m))
            await clock.sleep(0.2)
        elif what == "estop":
            m = robot.follow(plan, stretch_to_limits=True)
            await clock.sleep(0.3)
            await robot.estop(1)
            await clock.sleep(0.3)
            hasher.add(_result(m), [(e.kind, e.detail) for e in robot.safety.events])
        elif what == "speed":
            m = robot.follow(plan, stretch_to_limits=True)
            await clock.sleep(0.2)
            robot.set_speed_scaling(0.3)
            await clock.sleep(0.3)
            robot.set_speed_scaling(0.0)
            await clock.sleep(0.2)
            robot.set_speed_scaling(1.0)
            await m
            hasher.add(_result(m))
        elif what == "push":
            # an effort feed-forward of 30 % of the joints' effort limits pushes the
            # joints off their path while they follow with a tight path tolerance: the motion aborts
            # (PATH_TOLERANCE_VIOLATED) and stops from the measured state
            push_effort = np.array([0.3 * j.max_effort for j in robot.joints])
            m = robot.follow(plan, Tolerances(path=0.02, goal=0.01, goal_time=0.5), stretch_to_limits=True)
            def push(t: float, st: Any, sp: Any) -> None:
                if 0.1 <= t - m.start_time < 0.6:
                    sp.effort += push_effort

            handle = robot.add_tick_hook(Phase.COMMAND, push, order=1 << 20)
            await m
            handle.remove()
            await clock.sleep(0.2)
            hasher.add(_result(m), [(e.kind, e.detail) for e in robot.safety.events])
        elif what == "goal":
            # a goal tolerance no servo reaches within goal_time: GOAL_TOLERANCE_VIOLATED, then a stop
            m = robot.follow(plan, Tolerances(goal=1e-7, goal_time=0.05), stretch_to_limits=True)
            await m
            hasher.add(_result(m))
            await clock.sleep(0.2)
        elif what == "preempt":
            # a motion preempted by one scheduled to start later, itself started mid-run
            m = robot.follow(plan, stretch_to_limits=True)
            await clock.sleep(0.3)
            back = Trajectory(names, [TrajectoryPoint(0.9, start)])
            m2 = robot.follow(back, start_time=clock.now() + 0.0537, stretch_to_limits=True)
            await m
            await m2
            hasher.add(_result(m), _result(m2))
        elif what == "feedback":
            m = robot.follow(plan, stretch_to_limits=True)
            seen = [
                (fb.time, fb.progress, fb.desired_positions.tobytes(), fb.desired_velocities.tobytes(),
                 fb.actual_positions.tobytes(), fb.actual_velocities.tobytes(), fb.error.tobytes())
                async for fb in m.feedback(rate=137.0)
            ]
            hasher.add(_result(m), seen)
        elif what == "awaited":
            await _awaited_commands(robot, hasher, start)
        else:  # pragma: no cover
            raise AssertionError(what)
        return hasher.h.hexdigest(), hasher.ticks


async def _awaited_commands(robot: agentsdk.Robot, hasher: _Hasher, start: list[float]) -> None:
    """A behavior that reads and commands every tick (``read``, ``command``, ``sleep(period)``).

    Full-length position streams (small steps, with velocity and effort feed-forward), a subset of
    joints by name, jumps the step limiter ramps over several ticks, values outside the bounds
    (clamped), a velocity stream and back, rejected commands (unknown joint, NaN, wrong length) and
    an absurd velocity (clamped): the applied commands, the rejections and the safety events are
    hashed with the ticks.
    """
    clock, period = robot.clock, robot.control_period
    names = list(robot.joint_names)
    n = len(names)
    q0 = np.array(start)
    lo = np.array([j.lower if np.isfinite(j.lower) else -3.0 for j in robot.joints])
    hi = np.array([j.upper if np.isfinite(j.upper) else 3.0 for j in robot.joints])
    vmax = np.array([j.max_velocity for j in robot.joints])
    emax = np.array([j.max_effort for j in robot.joints])
    for k in range(240):
        state = await robot.read()
        hasher.add(k, state.position.tobytes(), state.velocity.tobytes())
        wave = 0.04 * np.sin(2.0 * np.pi * 0.5 * k * period + np.arange(n))
        phase = k // 20
        cmd: JointCommand
        if phase in (0, 5):
            cmd = JointCommand("position", (q0 + wave).tolist())
        elif phase == 1:
            cmd = JointCommand("position", (q0 + wave).tolist(), velocity=(0.1 * vmax).tolist(),
                               effort=(0.05 * emax * np.cos(k * 0.1)).tolist())
        elif phase == 2:
            sub = names[::2]
            cmd = JointCommand("position", {nm: float(q0[names.index(nm)] + wave[0]) for nm in reversed(sub)})
        elif phase == 3:
            # a jump of a quarter of each range every 10 ticks: the limiter ramps it over several ticks
            cmd = JointCommand("position", (lo + (hi - lo) * (0.35 + 0.25 * ((k // 10) % 2))).tolist())
        elif phase == 4:
            cmd = JointCommand("position", (hi + 0.2).tolist() if k % 2 else (lo - 0.2).tolist(),
                               velocity=(2.0 * vmax).tolist())
        elif phase == 6:
            cmd = JointCommand("velocity", (0.2 * np.cos(0.05 * k + np.arange(n))).tolist())
        elif phase == 7:
            cmd = JointCommand("velocity", {names[-1]: -0.1, names[0]: 0.15})
        elif phase == 8:
            cmd = JointCommand("position", (await robot.read()).position.tolist())
        else:
            cmd = JointCommand("position", (q0 - wave).tolist(), effort=(0.2 * emax).tolist())
        try:
            hasher.add(repr(await robot.command(cmd)))
        except agentsdk.AgentSDKError as exc:
            hasher.add(type(exc).__name__, str(exc))
        if k % 37 == 5:
            for bad in (JointCommand("position", {"no_such_joint": 0.0}),
                        JointCommand("position", [float("nan"), *start[1:]]),
                        JointCommand("position", start[:-1]),
                        JointCommand("velocity", [1e9] * n)):
                try:
                    hasher.add("accepted", repr(await robot.command(bad)))
                except agentsdk.AgentSDKError as exc:
                    hasher.add(type(exc).__name__, str(exc))
        await clock.sleep(period)
    hasher.add([(e.kind, e.detail, e.joint, e.time) for e in robot.safety.events])


def _result_of(r: Any) -> tuple[Any, ...]:
    return (r.code.name, r.message, r.time, sorted(r.error.items()))


def _load() -> dict[str, Any]:
    return json.loads(REFERENCE.read_text()) if REFERENCE.exists() else {}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("robot", ROBOTS)
async def test_tick_hashes_match_the_reference(backend: str, robot: str) -> None:
    try:
        load_backend(backend)
    except BackendUnavailableError:
        pytest.skip(f"{backend} not installed")
    ref = _load()
    key = f"{backend}/{robot}"
    fp = _fingerprint(backend)
    got = {}
    for what in SCENARIOS:
        digest, ticks = await _scenario(backend, robot, what)
        got[what] = f"{ticks}:{digest}"
    if UPDATE:
        ref.setdefault(key, {})[fp] = got
        REFERENCE.parent.mkdir(exist_ok=True)
        REFERENCE.write_text(json.dumps(ref, indent=1, sort_keys=True) + "\n")
        return
    # one reference per machine fingerprint (library versions and CPU features decide the bits)
    entry = ref.get(key, {}).get(fp)
    if entry is None:
        pytest.skip(f"no reference hashes for {key} on {fp} (AGENTSDK_UPDATE_TICK_HASHES=1 records them)")
    diff = {k: (entry.get(k), v) for k, v in got.items() if entry.get(k) != v}
    assert not diff, f"the tick computes other bits than the reference on {key}: {diff}"


@pytest.mark.timeout(300)
@pytest.mark.parametrize("what", ["follow", "speed", "push", "near_limits"])
async def test_the_executor_shortcut_changes_no_bit(what: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Differential: the same run with the executor's envelope shortcut (agentsdk.motion._envelope) and
    without it (every sample through the limiter) computes the same bits, wherever the machine is."""
    import agentsdk.motion._admission as admission

    try:
        load_backend("mujoco")
    except BackendUnavailableError:
        pytest.skip("mujoco not installed")
    run = _near_limits if what == "near_limits" else _scenario
    with_shortcut = await run("mujoco", "arm3", what)
    monkeypatch.setattr(admission, "envelope", lambda *args: None)
    without = await run("mujoco", "arm3", what)
    assert with_shortcut == without


async def _near_limits(backend: str, robot_name: str, what: str) -> tuple[str, int]:
    """Planned moves onto the position bounds and back: segments that touch a bound take the limiter's path."""
    async with agentsdk.connect(backend, robot=robot_name, safety={"stall_timeout": 30.0}) as robot:
        hasher = _Hasher(robot)
        names = list(robot.joint_names)
        margin = robot.safety.config.position_margin
        for frac in (1.0, 0.0, 0.5):
            goal = []
            for j in robot.joints:
                lo = j.lower if np.isfinite(j.lower) else -1.0
                hi = j.upper if np.isfinite(j.upper) else 1.0
                goal.append(min(max(lo + (hi - lo) * frac, lo + margin), hi - margin))
            hasher.add(_result_of(await robot.move_to(dict(zip(names, goal, strict=True)))))
        return hasher.h.hexdigest(), hasher.ticks
