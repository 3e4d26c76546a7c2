"""Block lockstep in the loop (issue 28 item 1, agentsdk.block): random runs hash tick for tick as without it.

Each case is a segment of a seeded random program on arm3 or humanoid (MuJoCo or PyBullet, lockstep), then a
sleep of random length (what blocks run): a move of random length and goal (``follow``, with a path
tolerance or none, on every joint or some, consecutive or not: several moves run at once; now or
scheduled later), a cancel of the running move (its stop ramp runs in blocks too), a speed scaling
factor, a feedback stream of the running move at a random rate, with a link's pose or not (hashed:
what it read), a direct position command (the filter's ramp: per tick, then blocks; refused while a
move drives the joints), an external push (MuJoCo's ``qfrc_applied``, on PyBullet a change of
gravity the servo's ``g(q)`` does not know; strong enough at random to trip the
path tolerance, the following-error or the measured-position check, or the plausibility gate, in the
middle of a block: a rollback), its release, or an e-stop of a random category (then mostly reset
and enable).
The same program runs with block lockstep off and on; every tick's time, setpoint and measured
state (an OBSERVE hook that takes blocks, :class:`agentsdk.block.BlockObserver`), and after each
segment the safety state and events, every move's latest feedback message and its result, are hashed;
the hashes must be equal segment by segment.
The test also demands that blocks ran and that some were cut short (so it exercises the path
it claims to test).
"""

from __future__ import annotations

import asyncio
import hashlib
from typing import Any

import mujoco
import numpy as np
import pytest

import agentsdk
from agentsdk import JointCommand, Phase, Tolerances, Trajectory, TrajectoryPoint
from agentsdk.block import BlockLockstep
from agentsdk.registry import load_backend

SAFETY = {"stall_timeout": 30.0}
#: seeds per robot and segments per seed: 2 x 13 x 40 = 1,040 cases
SEEDS, SEGMENTS = 13, 40
SEEDS_PYBULLET = 6
TRACE = False


class _Hasher:
    """sha256 of every tick's time, setpoint and measured state, per segment; takes blocks too."""

    def __init__(self) -> None:
        self.h = hashlib.sha256()
        self.ticks = 0

    def __call__(self, t: float, st: Any, sp: Any) -> None:
        self._one(t, (sp.position, sp.velocity, sp.effort, sp.kp, sp.kd, sp.target, sp.acceleration), sp,
                  st.position, st.velocity, st.effort)

    def observe_block(self, ts: np.ndarray, states: np.ndarray, rows: np.ndarray, sp: Any) -> None:
        for k in range(len(ts)):
            self._one(float(ts[k]), rows[k], sp, states[k, 0], states[k, 1], states[k, 2])

    def _one(self, t: float, rows: Any, sp: Any, q: np.ndarray, v: np.ndarray, e: np.ndarray) -> None:
        h = self.h
        h.update(np.float64(t).tobytes())
        for a in (*rows, sp.enabled, sp.mode, q, v, e):
            h.update(np.ascontiguousarray(a).tobytes())
        self.ticks += 1

    def cut(self, *items: Any) -> str:
        """The hash of the segment so far (and ``items``); starts the next segment."""
        self.h.update(repr(items).encode())
        out = self.h.hexdigest()
        self.h = hashlib.sha256()
        return out


def _message(fb: Any) -> tuple[Any, ...] | None:
    if fb is None:
        return None
    return (fb.time, fb.progress, fb.desired_positions.tobytes(), fb.desired_velocities.tobytes(),
            fb.actual_positions.tobytes(), fb.actual_velocities.tobytes(), fb.error.tobytes())


async def _stream(motion: Any, rate: float, seen: list[Any], links: tuple[str, ...]) -> None:
    async for fb in motion.feedback(rate=rate, links=links):
        poses = sorted((k, repr(p)) for k, p in (fb.poses or {}).items())
        seen.append((_message(fb), poses))


def _result(m: Any) -> tuple[Any, ...]:
    try:
        r = m.result()
    except Exception as exc:  # the motion failed (e.g. the loop faulted)
        return (repr(exc),)
    return (r.code.name, r.message, r.time, sorted(r.error.items()))


class _Push:
    """An external push: MuJoCo's ``qfrc_applied`` on some joints; on PyBullet a change of gravity (the
    servo law's ``g(q)`` still compensates the configured one), which PyBullet keeps until it changes."""

    def __init__(self, robot: Any) -> None:
        self.b = robot.backend
        self.mujoco = robot.backend.name == "mujoco"
        if self.mujoco:
            m = self.b.model
            self.dofs = np.array([m.jnt_dofadr[m.joint(name).id] for name in robot.joint_names])
        else:
            import pybullet

            self.p = pybullet
            self.g = np.array(self.b.options.gravity)

    def push(self, rng: np.random.Generator, j: np.ndarray, scale: float, effort: np.ndarray) -> None:
        if self.mujoco:
            self.b.data.qfrc_applied[self.dofs[j]] = rng.uniform(-scale, scale, len(j)) * effort[j]
        else:
            g = self.g + rng.uniform(-scale, scale, 3) * 9.81 * 2.0
            self.p.setGravity(*g.tolist(), physicsClientId=self.b._cid)

    def release(self) -> None:
        if self.mujoco:
            self.b.data.qfrc_applied[:] = 0.0
        else:
            self.p.setGravity(*self.g.tolist(), physicsClientId=self.b._cid)


async def _program(robot_name: str, seed: int, block: bool,
                   backend: str = "mujoco") -> tuple[list[str], dict[str, int]]:
    async with agentsdk.connect(backend, robot=robot_name, safety=SAFETY, block_lockstep=block) as robot:
        hasher = _Hasher()
        robot.add_tick_hook(Phase.OBSERVE, hasher, order=1 << 30)
        runner = robot.block_lockstep(capacity=128) if block else None
        rng = np.random.default_rng(seed)
        names = list(robot.joint_names)
        n = len(names)
        pusher = _Push(robot)
        lo = np.array([j.lower if np.isfinite(j.lower) else -1.0 for j in robot.joints])
        hi = np.array([j.upper if np.isfinite(j.upper) else 1.0 for j in robot.joints])
        effort = np.array([j.max_effort if 0 < j.max_effort < np.inf else 10.0 for j in robot.joints])
        out = []
        events = 0
        motion: Any = None
        streams: list[asyncio.Task[None]] = []
        motions: list[Any] = []
        seen: list[Any] = []
        for seg in range(SEGMENTS):
            what = str(rng.choice(["sleep", "sleep", "command", "follow", "follow", "follow", "cancel", "stream",
                                   "speed", "push", "push", "release", "estop"]))
            note = ""
            if what == "command" and robot.safety.state.name == "OK":
                goal = np.clip((await robot.read()).position + rng.uniform(-0.15, 0.15, n), lo, hi)
                try:
                    await robot.command(JointCommand("position", goal.tolist()))
                except agentsdk.errors.AgentSDKError as exc:  # a motion drives the joints
                    note = repr(exc)
            elif what == "follow" and robot.safety.state.name == "OK":
                # a move of random length from where the setpoint is, with a path tolerance or none
                # (mostly inside the limits by a margin: a segment that touches a bound runs tick by tick)
                margin = (hi - lo) * (0.1 if rng.random() < 0.8 else 0.0)
                goal = np.clip(np.asarray(robot.setpoint.position) + rng.uniform(-0.6, 0.6, n),
                               lo + margin, hi - margin)
                tol = (Tolerances(path=float(rng.choice([0.01, 0.05, 0.2])), goal=0.05, goal_time=0.5)
                       if rng.random() < 0.5 else None)
                # all joints, or some of them (consecutive or not; another motion may go on on the rest)
                part = np.arange(n) if rng.random() < 0.6 else np.sort(rng.choice(n, int(rng.integers(1, n)), False))
                if rng.random() < 0.5 and len(part) < n:
                    part = np.arange(int(part[0]), min(n, int(part[0]) + len(part)))
                plan = Trajectory([names[i] for i in part],
                                  [TrajectoryPoint(float(rng.uniform(0.1, 1.2)), goal[part].tolist())])
                # now, or scheduled to start later (it waits, then preempts what drives its joints)
                start = None if rng.random() < 0.7 else robot.clock.now() + float(rng.uniform(0.005, 0.3))
                try:
                    motion = robot.follow(plan, tol, stretch_to_limits=True, start_time=start)
                    motions.append(motion)
                except agentsdk.errors.AgentSDKError as exc:
                    note = repr(exc)
            elif what == "speed":
                # speed scaling: it ramps per tick, then a constant factor runs in blocks (0: paused)
                robot.set_speed_scaling(float(rng.choice([1.0, 1.0, 0.5, 0.3, 0.0, float(rng.uniform(0.1, 1.0))])))
            elif what == "cancel" and motion is not None and not motion.done():
                motion.cancel()
            elif what == "stream" and motion is not None and not motion.done():
                # a feedback stream at a random rate: it wakes between blocks and reads what they committed
                links = () if rng.random() < 0.5 else (robot.description.links[-1],)  # (+ link poses)
                streams.append(asyncio.create_task(_stream(motion, float(rng.uniform(20.0, 300.0)), seen, links)))
            elif what == "push":
                # a fraction of the joints' effort limits on a few of them, now and then more: a following
                # error, a limit hit or a reading the plausibility gate refuses, often in the middle of a block
                j = rng.choice(n, size=int(rng.integers(1, n + 1)), replace=False)
                scale = float(rng.choice([0.3, 0.8, 1.1, 1.6]))
                pusher.push(rng, j, scale, effort)
            elif what == "release":
                pusher.release()
            elif what == "estop":
                await robot.estop(int(rng.integers(0, 3)))
            await robot.clock.sleep(float(rng.choice([0.002, rng.uniform(0.0, 0.05), rng.uniform(0.05, 0.4)])))
            if rng.random() < 0.5:
                pusher.release()  # most pushes last one segment
            if robot.safety.state.name not in ("OK", "HOLD") and rng.random() < 0.85:
                pusher.release()
                await robot.safety.wait_stopped()
                await robot.reset()
                await robot.enable()
            new = robot.safety.events[events:] if len(robot.safety.events) >= events else ()
            events = len(robot.safety.events)
            if runner is not None and TRACE:
                print(seg, what, robot.safety.state.name, runner.blocks, runner.block_ticks, runner.rollbacks,
                      runner.motion_ticks, note[:60])
            # every move's latest feedback message and result (several may run, on different joints)
            feedback = [(_message(m._feedback), None if not m.done() else _result(m)) for m in motions]
            motions = [m for m in motions if not m.done()]
            out.append(hasher.cut(seg, what, note, robot.safety.state.name, robot.clock.ticks,
                                  [(e.kind, e.detail, e.joint, e.time) for e in new], feedback, seen))
            seen.clear()
        for task in streams:
            task.cancel()
        await asyncio.gather(*streams, return_exceptions=True)
        stats = {"ticks": hasher.ticks}
        if runner is not None:
            stats.update(blocks=runner.blocks, block_ticks=runner.block_ticks, rollbacks=runner.rollbacks,
                         motion_ticks=runner.motion_ticks)
            runner.close()
        return out, stats


@pytest.mark.timeout(900)
@pytest.mark.parametrize("robot_name", ["arm3", "humanoid"])
@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_block_lockstep_is_tick_by_tick_bit_for_bit(robot_name: str, backend: str) -> None:
    if backend == "pybullet":
        try:
            load_backend("pybullet")
        except agentsdk.errors.BackendUnavailableError:
            pytest.skip("pybullet is not installed")
    blocks = block_ticks = rollbacks = ticks = motion_ticks = 0
    # (PyBullet's ticks cost ~10x MuJoCo's: fewer seeds, 2 x 6 x 40 = 480 cases)
    for seed in range(SEEDS if backend == "mujoco" else SEEDS_PYBULLET):
        want, base = await _program(robot_name, seed, block=False, backend=backend)
        got, stats = await _program(robot_name, seed, block=True, backend=backend)
        for seg, (a, c) in enumerate(zip(want, got, strict=True)):
            assert a == c, f"{robot_name} on {backend} seed {seed}: segment {seg} differs with block lockstep"
        assert stats["ticks"] == base["ticks"]
        blocks += stats["blocks"]
        block_ticks += stats["block_ticks"]
        rollbacks += stats["rollbacks"]
        motion_ticks += stats["motion_ticks"]
        ticks += stats["ticks"]
    # the test exercises what it claims: most held ticks ran in blocks, and checks cut some blocks short
    assert blocks > 50 and block_ticks > ticks // 10 and motion_ticks > ticks // 100, (
        blocks, block_ticks, motion_ticks, ticks)
    assert rollbacks > 5, rollbacks


async def _diverge(block: bool) -> tuple[str, int, str, str]:
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY, block_lockstep=block) as robot:
        hasher = _Hasher()
        robot.add_tick_hook(Phase.OBSERVE, hasher, order=1 << 30)
        runner = robot.block_lockstep(capacity=64) if block else None
        b = robot.backend
        await robot.clock.sleep(0.2)
        b.data.qfrc_applied[:] = 1e300  # the next step's acceleration is not finite: SimulationDiverged
        with pytest.raises(agentsdk.errors.BackendFault):
            await robot.clock.sleep(0.3)
        fault = robot._loop.fault
        if runner is not None:
            assert runner.block_ticks > 0
            runner.close()
        return hasher.cut(), robot.clock.ticks, repr(fault), robot.safety.state.name


async def test_a_step_that_diverges_in_a_block_faults_as_tick_by_tick() -> None:
    assert await _diverge(True) == await _diverge(False)


async def _hold_or_move(robot: agentsdk.Robot, what: str) -> None:
    """The e-stop tests' half second: a hold, or a 0.3 rad move of every joint over 0.8 s."""
    if what == "move":
        q = (await robot.read()).position
        goal = [float(x) + 0.3 for x in q]
        robot.follow(Trajectory(list(robot.joint_names), [TrajectoryPoint(0.8, goal)]), stretch_to_limits=True)
    await robot.clock.sleep(0.5)


async def _thread_estop(block: bool, at: int, what: str, backend: str = "mujoco",
                        between_ticks: bool = False) -> tuple[Any, ...]:
    """An e-stop from another thread between tick ``at``'s write and its step (``between_ticks``: before its write)."""
    import threading

    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY, block_lockstep=block) as robot:
        hasher = _Hasher()
        robot.add_tick_hook(Phase.OBSERVE, hasher, order=1 << 30)
        if between_ticks:  # the last OBSERVE hook of tick at - 1 (which runs at robot time at * period)
            robot.add_tick_hook(Phase.OBSERVE, lambda t, st, sp: stop_at(t), order=(1 << 30) + 1)
        runner = robot.block_lockstep(capacity=64) if block else None
        b = robot.backend
        step = mujoco.mj_step
        fired = False
        if backend == "pybullet":
            import pybullet

            pb_step = pybullet.stepSimulation

        def stop_at(t: float) -> None:
            nonlocal fired
            if not fired and t >= (at - 0.5) * b.period:
                fired = True
                th = threading.Thread(target=robot.safety.estop_threadsafe, args=(0,))
                th.start()
                th.join()

        def stop_and_step(m: Any, d: Any, nstep: int = 1) -> None:
            stop_at(d.time)  # it lands between the write of tick ``at`` and its step
            step(m, d, nstep=nstep)

        def stop_and_step_pybullet(**kw: Any) -> None:
            stop_at(b._time)  # between two substeps (of tick ``at`` or the one before): the next one sees it
            pb_step(**kw)

        # a hold's block writes at its first tick only, a motion's puts each tick's controls computed
        # before the block: either way the e-stop comes between a tick's controls and its step (PyBullet:
        # its write every tick, then between the substeps, which read the enabled joints each)
        try:
            if between_ticks:
                pass
            elif backend == "pybullet":
                pybullet.stepSimulation = stop_and_step_pybullet
            else:
                mujoco.mj_step = stop_and_step
            await _hold_or_move(robot, what)
        finally:
            mujoco.mj_step = step
            if backend == "pybullet":
                pybullet.stepSimulation = pb_step
        loop = robot._loop
        assert fired and loop.torque_off and robot.safety.state.name == "ESTOP"
        assert not loop.setpoint.enabled.any()
        assert not (b._en.any() if backend == "pybullet" else b.data.ctrl.any())
        if runner is not None:
            assert 0 < runner.block_ticks < robot.clock.ticks
            assert what == "hold" or runner.motion_ticks > 0
            runner.close()
        events = [(e.kind, e.detail, e.time) for e in robot.safety.events]
        return hasher.cut(), robot.clock.ticks, events


@pytest.mark.parametrize("what", ["hold", "move"])
@pytest.mark.parametrize("at", [10, 45, 77])
@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
async def test_an_emergency_stop_from_another_thread_during_a_block_lands_as_tick_by_tick(
    at: int, what: str, backend: str,
) -> None:
    if backend == "pybullet":
        pytest.importorskip("pybullet")
    assert await _thread_estop(True, at, what, backend) == await _thread_estop(False, at, what, backend)


async def test_block_lockstep_is_refused_where_it_cannot_run_and_turns_off() -> None:
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY, realtime=True) as robot:
        with pytest.raises(agentsdk.errors.ConfigurationError, match="lockstep"):
            robot.block_lockstep()
    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        with pytest.raises(agentsdk.errors.InvalidValueError, match="capacity"):
            robot.block_lockstep(capacity=1)
        runner = robot.block_lockstep()  # on since connect: the same runner
        assert runner is robot.block_runner and runner.capacity == 256
        assert robot.block_lockstep() is runner
        with pytest.raises(agentsdk.errors.ConfigurationError, match="already on"):
            BlockLockstep(robot._loop, robot.safety.block_seam, None)  # one runner per loop
        await robot.clock.sleep(0.2)
        assert runner.block_ticks > 0
        runner.close()
        assert robot.block_runner is None and not runner.active
        ran = runner.block_ticks
        await robot.clock.sleep(0.2)
        assert runner.block_ticks == ran  # off: every tick runs on its own
        again = robot.block_lockstep(capacity=32)  # and it can be turned on again, of another size
        assert again is not runner and again.capacity == 32 and robot.block_runner is again
        await robot.clock.sleep(0.2)
        assert 0 < again.block_ticks and again.blocks * 32 >= again.block_ticks
        assert robot.block_lockstep(capacity=64) is not again and not again.active  # replaced
    assert robot.block_runner is None  # closing the robot turns it off
    with pytest.raises(agentsdk.errors.RobotClosedError):
        robot.block_lockstep()
    try:
        load_backend("pybullet")
    except agentsdk.errors.BackendUnavailableError:
        return
    async with agentsdk.connect("pybullet", robot="arm3", safety=SAFETY) as robot:
        runner = robot.block_runner  # PyBullet's block stepper (backends/pybullet/block.py): on by default
        assert runner is not None and runner.capacity == 256
        await robot.clock.sleep(0.2)
        assert runner.block_ticks > 0


async def _rollout_estop(at: int, what: str) -> tuple[Any, ...]:
    """:func:`_thread_estop`'s run with the e-stop from another thread inside a block's rollout.

    The e-stop comes when the rollout of the block that holds tick ``at`` is called, after the
    block's first write: ``stop()`` sees it after the rollout, as one that landed during it.

    Returns what :func:`_thread_estop` returns and the tick the block that saw it started at.
    """
    import threading

    from agentsdk.backends.mujoco import block as mujoco_block

    async with agentsdk.connect("mujoco", robot="arm3", safety=SAFETY) as robot:
        hasher = _Hasher()
        robot.add_tick_hook(Phase.OBSERVE, hasher, order=1 << 30)
        runner = robot.block_lockstep(capacity=64)
        b = robot.backend
        inside: list[int] = []  # the tick the running rollout's block started at
        fired: list[int] = []
        open_loop = mujoco_block.BlockStepper._run_open_loop

        def spy(self: Any, *args: Any) -> Any:
            inside.append(robot.clock.ticks)
            try:
                return open_loop(self, *args)
            finally:
                inside.pop()

        rollout = mujoco_block.mujoco_rollout.Rollout.rollout

        def rollout_spy(self: Any, model: Any, data: Any, *args: Any, **kw: Any) -> Any:
            t0 = data[0].time  # the block's first step starts here; it runs nstep physics steps
            t_at = (at - 0.5) * b.period
            if inside and not fired and t0 <= t_at < t0 + kw["nstep"] * model[0].opt.timestep:
                fired.append(inside[-1])
                th = threading.Thread(target=robot.safety.estop_threadsafe, args=(0,))
                th.start()
                th.join()
            return rollout(self, model, data, *args, **kw)

        mujoco_block.BlockStepper._run_open_loop = spy  # type: ignore[method-assign]
        mujoco_block.mujoco_rollout.Rollout.rollout = rollout_spy  # type: ignore[method-assign]
        try:
            await _hold_or_move(robot, what)
        finally:
            mujoco_block.mujoco_rollout.Rollout.rollout = rollout  # type: ignore[method-assign]
            mujoco_block.BlockStepper._run_open_loop = open_loop  # type: ignore[method-assign]
        loop = robot._loop
        assert fired and fired[0] < at, (fired, at)  # it landed inside a rollout, after the block's start
        assert loop.torque_off and robot.safety.state.name == "ESTOP"
        assert not loop.setpoint.enabled.any()
        assert not b.data.ctrl.any()
        assert runner.block_ticks <= fired[0] < robot.clock.ticks  # (the rolled-back block is not counted)
        runner.close()
        events = [(e.kind, e.detail, e.time) for e in robot.safety.events]
        return hasher.cut(), robot.clock.ticks, events, fired[0]


@pytest.mark.parametrize("what", ["hold", "move"])
@pytest.mark.parametrize("at", [45, 77])
async def test_an_emergency_stop_during_a_rollout_lands_before_the_blocks_first_tick(at: int, what: str) -> None:
    """An e-stop from another thread while a block runs as one rollout lands at the tick the block started from.

    The rollout is undone (MuJoCo back to before that tick's write) and the run goes on as a
    tick-by-tick run whose e-stop landed there: the same ticks, states, setpoints and events.
    """
    *got, start = await _rollout_estop(at, what)
    assert tuple(got) == await _thread_estop(False, start, what, between_ticks=True)


#: a two-joint arm beside boxes that fall into a pile in too small an arena: once they touch, MuJoCo drops
#: constraints (and counts mjWARN_CNSTRFULL) at every physics step, and logs that warning the first time only
CROWDED_MJCF = """<mujoco model="crowded">
  <compiler angle="radian"/>
  <size memory="48K"/>
  <worldbody>
    <geom type="plane" size="5 5 .1"/>
    <body name="link1" pos="-1 0 1">
      <joint name="j1" type="hinge" axis="0 1 0" range="-2 2"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      <body name="link2" pos="0.3 0 0">
        <joint name="j2" type="hinge" axis="0 1 0" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      </body>
    </body>
""" + "".join(
    f'    <body pos="{0.11 * i:.2f} {0.11 * j:.2f} {1.3 + 0.11 * k:.2f}"><freejoint/>'
    '<geom type="box" size=".05 .05 .05"/></body>\n'
    for i in range(3) for j in range(2) for k in range(1 + (j == 0))
) + """  </worldbody>
  <actuator><motor joint="j1" name="j1"/><motor joint="j2" name="j2"/></actuator>
</mujoco>
"""


async def test_a_warning_at_every_step_is_logged_once_and_the_blocks_stay_tick_by_tick_bit_for_bit(
    tmp_path: Any, caplog: pytest.LogCaptureFixture,
) -> None:
    """A rollout clears MuJoCo's warning counters: blocks of a model that warns must not log the warning again.

    Before: the first block's rollout logged the warning, the block's run tick by tick after it logged it
    again, and every later block's rollout logged it once more (6 lines for one warning in this run).
    """
    from agentsdk.backends.mujoco import block as mujoco_block

    path = tmp_path / "crowded.xml"
    path.write_text(CROWDED_MJCF)
    rollouts: list[float] = []
    rollout = mujoco_block.mujoco_rollout.Rollout.rollout

    def rollout_spy(self: Any, model: Any, data: Any, *args: Any, **kw: Any) -> Any:
        rollouts.append(data[0].time)
        return rollout(self, model, data, *args, **kw)

    async def run(block: bool) -> tuple[bytes, list[str]]:
        caplog.clear()
        async with agentsdk.connect("mujoco", str(path), safety=SAFETY, block_lockstep=block) as robot:
            hasher = _Hasher()
            robot.add_tick_hook(Phase.OBSERVE, hasher, order=1 << 30)
            await robot.command(JointCommand("position", [0.2, -0.3]))
            await robot.clock.sleep(0.7)
            await robot.follow(Trajectory(["j1", "j2"], [TrajectoryPoint(1.5, [0.5, 0.1])]))
            await robot.clock.sleep(0.3)
            d = robot.backend.data
            counted = d.warning.number[int(mujoco.mjtWarning.mjWARN_CNSTRFULL)]
            assert counted > 0.5 * robot.clock.ticks * robot.backend._nsub  # (it warns at every step once piled)
            state = hasher.cut().encode() + d.qpos.tobytes() + d.qvel.tobytes()
            warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("MuJoCo:")]
            return state + d.warning.number.tobytes() + d.warning.lastinfo.tobytes(), warned

    mujoco_block.mujoco_rollout.Rollout.rollout = rollout_spy  # type: ignore[method-assign]
    try:
        with caplog.at_level("WARNING", logger="agentsdk.backends.mujoco"):
            blocks, logged_blocks = await run(True)
            # the rollouts of the blocks before the boxes touch, and the one of the block where they do: after
            # it, MuJoCo has counted the warning
            assert rollouts and rollouts[-1] < 0.5
            n_rollouts = len(rollouts)
            ticks, logged_ticks = await run(False)
    finally:
        mujoco_block.mujoco_rollout.Rollout.rollout = rollout  # type: ignore[method-assign]
    assert len(rollouts) == n_rollouts
    assert len(logged_ticks) == 1 and "arena" in logged_ticks[0]
    assert logged_blocks == logged_ticks
    assert blocks == ticks
