"""Backend conformance kit: the executable contract every backend must pass.

Use it from any test suite (ours or a third-party backend's)::

    # tests/test_my_backend.py
    from agentsdk.testing import BackendConformance

    class TestMyBackend(BackendConformance):
        backend = "mybackend"          # the entry-point name
        robot = "arm3"                 # a robot name or a .urdf/.xacro/robot.yaml path
        connect_options = {"port": "/dev/ttyACM0"}

Override :meth:`BackendConformance.open_robot` when the backend needs a fixture
around it (a motor emulator, a simulator process). Tests are gated on the
capabilities the backend declares (``Controller.capabilities``), never on its
name; capabilities are read from the opened robot (a backend may declare them
per instance). Requires ``pytest`` and ``pytest-asyncio``.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import threading
import time
from collections.abc import AsyncIterator
from typing import Any, ClassVar

import numpy as np
import pytest

from .backend import Capabilities
from .description import apply_overrides, resolve_robot
from .errors import (
    AgentSDKError,
    InvalidValueError,
    RobotClosedError,
    SafetyFault,
    SensorFault,
    UnknownJointError,
    UnsupportedModeError,
)
from .loop import Phase
from .registry import load_backend
from .robot import Robot, connect
from .safety import SafetyState
from .types import MODES, JointCommand

__all__ = ["BackendConformance", "SensorConformance"]

#: keywords of :func:`agentsdk.connect` itself (the rest of ``connect_options`` go to the backend)
_CONNECT_KEYWORDS = frozenset({"realtime", "safety", "strict", "trusted"})


def _block(seconds: float) -> None:
    """Block the calling thread (the event loop's): what the loop-stall watchdog must catch."""
    time.sleep(seconds)


def _mid_target(robot: Robot, j: int, offset: float = 0.3) -> float:
    """A reachable target ``offset`` away from the joint's neutral position, strictly inside its limits."""
    info = robot.joints[j]
    lo = info.lower if math.isfinite(info.lower) else -10.0
    hi = info.upper if math.isfinite(info.upper) else 10.0
    margin = min(0.05, (hi - lo) / 4)
    center = min(max(0.0, lo + margin), hi - margin)
    for target in (center + offset, center - offset):
        if lo + margin <= target <= hi - margin:
            return target
    return min(max(center + offset, lo + margin), hi - margin)


class BackendConformance:
    """Subclass with ``backend = "<name>"``; every ``test_*`` method is one clause of the contract."""

    # (a class attribute, not a class decorator: the API reference is built without pytest, which
    # Sphinx then mocks, and a mocked decorator would replace the class)
    pytestmark: ClassVar[Any] = pytest.mark.asyncio
    backend: ClassVar[str] = ""
    robot: ClassVar[str] = "arm3"
    connect_options: ClassVar[dict[str, Any]] = {}
    realtime: ClassVar[bool | None] = None
    #: how long (robot seconds) a mode may take to reach its target
    settle_time: ClassVar[float] = 3.0
    position_tolerance: ClassVar[float] = 0.02
    velocity_tolerance: ClassVar[float] = 0.1
    effort_tolerance: ClassVar[float] = 0.05

    # ----------------------------------------------------------- hooks
    @contextlib.asynccontextmanager
    async def open_robot(self, **overrides: Any) -> AsyncIterator[Robot]:
        """Connect a robot on the backend under test. Override to add fixtures."""
        opts = {**self.connect_options, **overrides}
        async with connect(self.backend, robot=self.robot, realtime=self.realtime, **opts) as robot:
            yield robot

    def capabilities(self) -> Capabilities:
        """The capabilities the backend declares for this configuration (read from an instance)."""
        cached: Capabilities | None = type(self).__dict__.get("_caps")
        if cached is not None:
            return cached
        config, desc = resolve_robot(self.robot)
        cls = load_backend(self.backend)
        # (connect()'s own keywords, e.g. ``safety``, are not backend options)
        backend_options = {k: v for k, v in self.connect_options.items() if k not in _CONNECT_KEYWORDS}
        instance = cls.create(config, desc, apply_overrides(desc, config), realtime=self.realtime, **backend_options)
        caps: Capabilities = instance.capabilities
        type.__setattr__(type(self), "_caps", caps)
        return caps

    # ------------------------------------------------------- metadata
    async def test_joint_metadata_matches_description(self) -> None:
        """Joint names, types and limits read from the backend match the robot description."""
        config, desc = resolve_robot(self.robot)
        expected = apply_overrides(desc, config)
        async with self.open_robot() as robot:
            assert [j.name for j in robot.joints] == [j.name for j in expected]
            for got, want in zip(robot.joints, expected, strict=True):
                assert got.type == want.type, got.name
                assert got.lower == want.lower and got.upper == want.upper, got.name
                assert got.max_velocity == want.max_velocity, got.name
                assert got.max_effort == want.max_effort, got.name

    async def test_read_is_finite_and_well_shaped(self) -> None:
        """The first read returns finite positions, velocities and efforts, one per joint."""
        async with self.open_robot() as robot:
            await robot.clock.sleep(0.05)
            st = await robot.read()
            n = len(robot.joints)
            assert st.names == tuple(j.name for j in robot.joints)
            for arr in (st.position, st.velocity, st.effort):
                assert arr.shape == (n,)
                assert np.isfinite(arr).all()
            assert math.isfinite(st.stamp)

    # ---------------------------------------------------------- modes
    async def _reach(self, robot: Robot, predicate: Any, what: str) -> None:
        deadline = robot.clock.now() + self.settle_time
        while robot.clock.now() < deadline:
            await robot.clock.sleep(0.02)
            st = await robot.read()
            if predicate(st):
                return
        st = await robot.read()
        pytest.fail(f"{what} not reached within {self.settle_time} s: state {st}")

    async def test_position_mode_reaches_target(self) -> None:
        """A position command is reached within tolerance."""
        if "position" not in self.capabilities().modes:
            pytest.skip("backend does not declare position mode")
        async with self.open_robot() as robot:
            target = {j.name: _mid_target(robot, k, 0.2) for k, j in enumerate(robot.joints)}
            await robot.command(JointCommand("position", target))
            want = np.array(list(target.values()))
            tol = self.position_tolerance
            await self._reach(robot, lambda st: np.all(np.abs(st.position - want) < tol), "position target")

    async def test_velocity_mode_reaches_target(self) -> None:
        """A velocity command is tracked."""
        if "velocity" not in self.capabilities().modes:
            pytest.skip("backend does not declare velocity mode")
        async with self.open_robot() as robot:
            j = robot.joints[0]
            v = 0.2 * min(j.max_velocity, 2.0)
            tol = self.velocity_tolerance

            async def keep_streaming() -> None:  # velocity commands are watched: stream them
                while True:
                    await robot.command(JointCommand("velocity", {j.name: v}))
                    await robot.clock.sleep(0.02)

            async with asyncio.TaskGroup() as tg:
                streamer = tg.create_task(keep_streaming())
                try:
                    await self._reach(robot, lambda st: abs(st.velocity[0] - v) < tol, f"velocity {v} on {j.name}")
                finally:
                    streamer.cancel()

    async def test_effort_mode_applies_effort(self) -> None:
        """The measured effort matches a commanded effort of 5 % of the limit."""
        if "effort" not in self.capabilities().modes:
            pytest.skip("backend does not declare effort mode")
        async with self.open_robot() as robot:
            j = robot.joints[0]
            tau = 0.05 * j.max_effort
            tol = max(self.effort_tolerance * j.max_effort, 1e-3)
            applied = await robot.command(JointCommand("effort", {j.name: tau}))
            assert applied.values[j.name] == pytest.approx(tau)
            await robot.clock.sleep(0.05)
            st = await robot.read()
            assert abs(st.effort[0] - tau) < tol, f"effort on {j.name}: {st.effort[0]} != {tau}"

    async def test_undeclared_mode_is_rejected(self) -> None:
        """A mode the backend does not declare is rejected with a specific error."""
        undeclared = [m for m in MODES if m not in self.capabilities().modes]
        if not undeclared:
            pytest.skip("backend declares every command mode")
        async with self.open_robot() as robot:
            j = robot.joints[0].name
            for mode in undeclared:
                with pytest.raises(UnsupportedModeError, match=mode):
                    await robot.command(JointCommand(mode, {j: 0.0}))

    # ---------------------------------------------------------- clock
    async def test_clock_is_monotonic_and_sleep_advances(self) -> None:
        """The clock never goes backwards and ``sleep`` advances it."""
        async with self.open_robot() as robot:
            t0 = robot.clock.now()
            seen = [t0]
            for _ in range(5):
                await robot.clock.sleep(0.01)
                seen.append(robot.clock.now())
            assert all(b > a for a, b in itertools.pairwise(seen)), seen
            assert seen[-1] - t0 >= 0.05 - 1e-9
            st = await robot.read()
            assert st.stamp <= robot.clock.now() + 1e-9

    # ---------------------------------------------------------- close
    async def test_close_is_idempotent_and_later_calls_raise(self) -> None:
        """``close()`` is idempotent and later commands raise ``RobotClosedError``."""
        threads_before = set(threading.enumerate())
        tasks_before = set(asyncio.all_tasks())
        async with self.open_robot() as robot:
            await robot.clock.sleep(0.02)
        await robot.close()
        await robot.close()
        j = robot.joints[0].name
        with pytest.raises(RobotClosedError):
            await robot.read()
        with pytest.raises(RobotClosedError):
            await robot.command(JointCommand("position", {j: 0.0}))
        with pytest.raises(RobotClosedError):
            await robot.estop()
        for _ in range(3):
            await asyncio.sleep(0)
        leaked_tasks = [t for t in asyncio.all_tasks() - tasks_before if not t.done()]
        assert not leaked_tasks, f"tasks left running after close(): {leaked_tasks}"
        leaked = [t for t in set(threading.enumerate()) - threads_before if t.is_alive()]
        for t in leaked:
            t.join(timeout=1.0)
        alive = [t.name for t in leaked if t.is_alive()]
        assert not alive, f"threads left running after close(): {alive}"

    # ----------------------------------------------------- concurrency
    async def test_concurrent_commands_are_serialized(self) -> None:
        """Commands from concurrent tasks are applied one at a time, none lost."""
        if "position" not in self.capabilities().modes:
            pytest.skip("needs position mode")
        async with self.open_robot() as robot:
            n = len(robot.joints)
            a = [_mid_target(robot, k, 0.1) for k in range(n)]
            b = [_mid_target(robot, k, -0.1) for k in range(n)]
            for _ in range(20):
                ra, rb = await asyncio.gather(
                    robot.command(JointCommand("position", a)), robot.command(JointCommand("position", b))
                )
                assert list(ra.values.values()) == pytest.approx(a)
                assert list(rb.values.values()) == pytest.approx(b)
                target = robot.command_targets()
                assert np.allclose(target, a) or np.allclose(target, b), f"interleaved setpoint {target}"

    # ----------------------------------------------------- determinism
    async def _trajectory(self) -> list[np.ndarray]:
        async with self.open_robot() as robot:
            out = []
            n = len(robot.joints)
            await robot.command(JointCommand("position", [_mid_target(robot, k, 0.25) for k in range(n)]))
            for _ in range(30):
                await robot.clock.sleep(0.01)
                out.append((await robot.read()).position)
            return out

    async def test_lockstep_is_deterministic(self) -> None:
        """Two lockstep runs of the same commands give identical states (skipped unless declared deterministic)."""
        caps = self.capabilities()
        if not (caps.lockstep and caps.deterministic) or self.realtime:
            pytest.skip("backend is not a deterministic lockstep backend")
        first = await self._trajectory()
        second = await self._trajectory()
        for x, y in zip(first, second, strict=True):
            assert np.array_equal(x, y)

    # ----------------------------------------------------- cancellation
    async def test_cancelled_waiter_leaves_backend_usable(self) -> None:
        """A waiter cancelled mid-wait leaves the backend usable."""
        async with self.open_robot() as robot:

            async def waiter() -> None:
                await robot.clock.sleep(100.0)

            task = asyncio.get_running_loop().create_task(waiter())
            await robot.clock.sleep(0.02)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            t0 = robot.clock.now()
            await robot.clock.sleep(0.02)
            assert robot.clock.now() > t0
            j = robot.joints[0].name
            await robot.command(JointCommand("position" if "position" in self.capabilities().modes
                                             else sorted(self.capabilities().modes)[0], {j: 0.0}))
            assert np.isfinite((await robot.read()).position).all()

    # ------------------------------------------------------- torque off
    async def _push(self, robot: Robot) -> tuple[str, float]:
        """Apply a clear effort on the first joint and check it shows in the measured effort."""
        j = robot.joints[0]
        tau = 0.2 * j.max_effort
        await robot.command(JointCommand("effort", {j.name: tau}))
        await robot.clock.sleep(max(0.03, 3 * robot.control_period))
        st = await robot.read()
        assert abs(st.effort[0] - tau) < 0.25 * tau, f"effort on {j.name}: {st.effort[0]} != {tau}"
        return j.name, tau

    async def _ticks(self, robot: Robot, n: int) -> None:
        target = robot.ticks + n
        while robot.ticks < target:
            await robot.clock.sleep(robot.control_period)

    async def test_threadsafe_estop_removes_torque_within_one_tick(self) -> None:
        """An e-stop requested from another thread removes torque within one tick."""
        if "effort" not in self.capabilities().modes:
            pytest.skip("needs effort mode to observe the actuator torque")
        async with self.open_robot() as robot:
            name, tau = await self._push(robot)
            button = threading.Thread(target=robot.estop_threadsafe, args=(0,), name="conformance-estop-button")
            button.start()
            while button.is_alive():  # noqa: ASYNC110 - waiting for a plain thread without blocking the loop
                await asyncio.sleep(0.001)
            button.join()
            assert not robot.torque_enabled
            # lockstep: no tick ran meanwhile, the next one writes torque off; realtime: a tick in
            # flight when the stop landed may still show the old torque
            await self._ticks(robot, 2 if robot.realtime else 1)
            st = await robot.read()
            assert abs(st.effort[0]) < 0.25 * tau, f"{name} still has effort {st.effort[0]} after an e-stop"
            assert not robot.setpoint.enabled.any()

    async def test_loop_stall_is_detected_and_removes_torque(self) -> None:
        """A blocked event loop is detected by the stall watchdog, which removes torque."""
        if "effort" not in self.capabilities().modes:
            pytest.skip("needs effort mode to observe the actuator torque")
        timeout = 0.1
        # stall_in_lockstep: a lockstep backend's watchdog is off by default (simulated time stops with the loop)
        async with self.open_robot(safety={"stall_timeout": timeout, "stall_in_lockstep": True}) as robot:
            name, tau = await self._push(robot)
            _block(6 * timeout)  # a behavior that blocks the event loop
            assert robot.safety.state.name == "ESTOP"
            assert any(e.kind == "stall" for e in robot.safety.events), robot.safety.events
            assert not robot.torque_enabled
            await self._ticks(robot, 2 if robot.realtime else 1)
            st = await robot.read()
            assert abs(st.effort[0]) < 0.25 * tau, f"{name} still has effort {st.effort[0]} after a stall"

    # ----------------------------------------------------- sensor faults
    async def test_implausible_reading_is_a_sensor_fault_and_never_steps_the_setpoint(self) -> None:
        """A reading the physics cannot explain (far past a limit in one step, NaN) is a sensor fault.

        It latches FAULT with a :class:`SensorFault` naming the joint and the backend's
        ``joint_source`` (the motor on a bus) within 0.5 s, the state keeps the last plausible
        value, and the stop starts from the reference: no setpoint steps by more than the joint
        may move in the time between two ticks. ``reset`` and ``enable`` recover.
        """
        for kind in ("jump", "nan"):
            async with self.open_robot() as robot:
                await self._check_sensor_fault(robot, kind)

    async def _check_sensor_fault(self, robot: Robot, kind: str) -> None:
        backend = robot.backend
        joints = robot.joints
        j = next((k for k, info in enumerate(joints) if math.isfinite(info.upper)), 0)
        name = joints[j].name
        upper = joints[j].upper if math.isfinite(joints[j].upper) else 0.0
        await robot.clock.sleep(0.1)
        inject = [False]
        real_read = backend._read

        def faulty_read() -> Any:
            q, v, e = real_read()
            if inject[0]:
                inject[0] = False
                q = np.array(q, dtype=float)
                q[j] = upper + 10.0 if kind == "jump" else math.nan
            return q, v, e

        log: list[tuple[float, np.ndarray, np.ndarray]] = []

        def observe(t: float, st: Any, sp: Any) -> None:
            log.append((t, st.position.copy(), sp.position.copy()))

        backend._read = faulty_read  # type: ignore[method-assign]  # the instance's hook, for this test
        handle = robot.add_tick_hook(Phase.OBSERVE, observe)
        try:
            inject[0] = True
            deadline = robot.clock.now() + 0.5
            while robot.safety.state is not SafetyState.FAULT:
                assert robot.clock.now() < deadline, f"{kind}: no sensor fault within 0.5 s ({robot.safety.events})"
                await robot.clock.sleep(robot.control_period)
            await robot.safety.wait_stopped()
        finally:
            handle.remove()
            del backend._read
        cause = robot.safety.cause
        assert isinstance(cause, SensorFault), f"{kind}: cause {cause!r}"
        source = backend.joint_source(j)
        assert cause.joint == name and cause.source == source
        assert name in str(cause) and (source is None or source in str(cause))
        assert any(e.kind == "sensor" and e.joint == name for e in robot.safety.events)
        with pytest.raises(SafetyFault):
            await robot.read()
        assert np.isfinite(robot.latest_state().position).all()
        vmax = np.array([info.max_velocity for info in joints])
        for (t0, _, sp0), (t1, st1, sp1) in itertools.pairwise(log):
            assert np.isfinite(st1).all() and st1[j] < upper + 5.0, f"{kind}: the implausible value reached the state"
            bound = vmax * max(t1 - t0, robot.control_period) * (1 + 1e-6) + 1e-6
            step = np.abs(sp1 - sp0)
            bad = np.isfinite(vmax) & (step > bound)
            assert not bad.any(), f"{kind}: setpoint stepped {step[bad]} (bound {bound[bad]}) at t={t1:.3f}"
        await robot.reset()
        await robot.enable()
        assert robot.safety.state.name == "OK"

    # ------------------------------------------------------- bad input
    async def test_bad_input_is_rejected_and_state_unchanged(self) -> None:
        """Unknown joints, NaN and out-of-limit values are rejected and leave the state unchanged."""
        mode = "position" if "position" in self.capabilities().modes else sorted(self.capabilities().modes)[0]
        async with self.open_robot() as robot:
            await robot.clock.sleep(0.02)
            before = robot.command_targets()
            n = len(robot.joints)
            j = robot.joints[0].name
            bad: list[tuple[type[AgentSDKError], JointCommand]] = [
                (UnknownJointError, JointCommand(mode, {"no_such_joint": 0.0})),
                (InvalidValueError, JointCommand(mode, {j: float("nan")})),
                (InvalidValueError, JointCommand(mode, {j: float("inf")})),
                (InvalidValueError, JointCommand(mode, [0.0] * (n + 1))),
            ]
            for exc_type, cmd in bad:
                with pytest.raises(exc_type):
                    await robot.command(cmd)
                assert np.array_equal(robot.command_targets(), before), f"state changed by {cmd}"
            # still usable
            await robot.command(JointCommand(mode, {j: 0.0}))
            await robot.clock.sleep(0.02)
            assert np.isfinite((await robot.read()).position).all()


class SensorConformance:
    """The sensor clauses of the contract: subclass with ``backend`` and a ``robot`` that declares sensors.

    Every sensor the backend lists reads a value of its kind's shape, stamped on the robot's clock at
    a sample time, attached to a link of the robot, with finite numbers (a range may be ``inf``:
    nothing in range); a deterministic lockstep backend samples identically in two runs.
    """

    backend: ClassVar[str] = ""
    robot: ClassVar[str] = ""
    connect_options: ClassVar[dict[str, Any]] = {}
    #: sensors the backend must serve (a subset of the robot's declared ones)
    expected_sensors: ClassVar[tuple[str, ...]] = ()

    @contextlib.asynccontextmanager
    async def open_robot(self) -> AsyncIterator[Robot]:
        """Connect a robot on the backend under test (lockstep where the backend can)."""
        async with connect(self.backend, robot=self.robot, **self.connect_options) as robot:
            yield robot

    async def _samples(self) -> dict[str, np.ndarray]:
        async with self.open_robot() as robot:
            await robot.clock.sleep(0.1)
            return {name: robot.sensors.values(name).copy() for name in robot.sensors.names}

    async def test_sensors_read_well_formed_values(self) -> None:
        """Each listed sensor: its kind's layout, a link frame, a stamp at a sample time, finite values."""
        from .sensors import KINDS, Image

        async with self.open_robot() as robot:
            listed = robot.sensors.names
            assert set(self.expected_sensors) <= set(listed), listed
            assert len(set(listed)) == len(listed)
            await robot.clock.sleep(0.1)
            now = robot.clock.now()
            links = set(robot.description.links)
            for info in robot.sensors:
                reading = robot.sensors.read(info.name)
                header = reading.header
                assert header.frame_id == info.frame_id and header.frame_id in links, info
                assert math.isfinite(header.stamp) and 0.0 <= header.stamp <= now + 1e-9, (info, header)
                values = robot.sensors.values(info.name)
                if info.type == "camera":
                    assert isinstance(reading, Image) and reading.data.shape[2] == 3
                    continue
                expected = info.spec.size if info.type == "lidar" else KINDS[info.type]
                assert values.shape == (expected,), info
                finite = np.isfinite(values) | (np.isposinf(values) & (info.type in ("rangefinder", "lidar")))
                assert finite.all(), (info.name, values)
                if info.type in ("imu", "orientation"):
                    assert abs(float(np.linalg.norm(values[0:4])) - 1.0) < 1e-6, (info.name, values)

    async def test_sensor_sampling_is_deterministic_in_lockstep(self) -> None:
        """Two lockstep runs sample every sensor identically (skipped unless the backend is deterministic)."""
        async with self.open_robot() as robot:
            caps = robot.capabilities
            if not (caps.lockstep and caps.deterministic) or robot.realtime:
                pytest.skip("backend is not a deterministic lockstep backend")
        first = await self._samples()
        second = await self._samples()
        assert first.keys() == second.keys()
        for name, values in first.items():
            assert np.array_equal(values, second[name]), name
