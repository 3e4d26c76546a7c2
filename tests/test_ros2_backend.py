"""Issue 23 acceptance 1 (and the ``ros2`` backend's own rules): behaviors run unchanged over ROS 2.

``agentsdk serve --backend mujoco --lockstep`` runs in another process on a random ROS domain
(loopback only: the served side's own loopback config); ``connect("ros2")`` drives it, each tick
stepping the served robot by one control period, so a lockstep behavior ends where it ends on a
local ``connect("mujoco")``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

import test_ros2_interop as interop
from ros_domains import random_domain

import agentsdk
from agentsdk import BackendFault, BackendStartError, ConfigurationError, JointCommand, SafetyFault
from agentsdk.cli import load_behavior
from agentsdk.ros2 import expose
from agentsdk.ros2.dds import DdsNode
from agentsdk.ros2.msgs import CancelGoal_Request, CancelGoal_Response, Header, JointState, JointTrajectory
from agentsdk.ros2.stream import COMMAND_TOPIC, QOS_STREAM, STATE_TOPIC

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(300)]

#: the Fast DDS peer's build and a random loopback domain with its peers' environment (test_ros2_interop's fixtures)
domain = interop.domain
fastdds_peer = interop.fastdds_peer
Domain = interop.Domain

SAFETY = {"stall_timeout": 5.0}  # a loaded 2-core machine also runs the server process


def _domain() -> int:
    return random_domain()


class Served:
    def __init__(self, proc: asyncio.subprocess.Process, domain_id: int) -> None:
        self.proc = proc
        self.domain_id = domain_id


async def _stop(proc: asyncio.subprocess.Process) -> None:
    """SIGTERM, then SIGKILL after 30 s; returns once the process has exited."""
    if proc.returncode is None:
        proc.terminate()
        try:
            async with asyncio.timeout(30):
                await proc.wait()
        except TimeoutError:
            proc.kill()
            await proc.wait()


@contextlib.asynccontextmanager
async def _serve(*args: str, domain_id: int) -> AsyncIterator[Served]:
    """``agentsdk serve ARGS`` in another process, until it says it serves each ``--robot``.

    Its log (stderr) is read all along: a full pipe would block the served robot mid-tick. When the
    body fails, the log's tail is printed, so a rejected goal or a fault shows the served side's reason.
    """
    env = {k: v for k, v in os.environ.items() if k != "CYCLONEDDS_URI"}
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(agentsdk.__file__).parents[1]), env.get("PYTHONPATH", "")])
    proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "agentsdk", "serve", *args, env=env,
                                                stderr=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.DEVNULL)
    stderr = proc.stderr
    assert stderr is not None
    log: list[str] = []

    async def drain() -> None:
        while line := (await stderr.readline()).decode():
            log.append(line)

    drainer: asyncio.Task[None] | None = None
    failed = False
    try:
        robots = args.count("--robot")
        serving = 0
        async with asyncio.timeout(90):
            while serving < robots:
                line = (await stderr.readline()).decode()
                log.append(line)
                assert line, "agentsdk serve exited before serving:\n" + "".join(log)
                serving += "serving" in line
        drainer = asyncio.create_task(drain())
        yield Served(proc, domain_id)
    except BaseException:
        failed = True
        raise
    finally:
        await _stop(proc)
        if drainer is not None:
            try:
                async with asyncio.timeout(10):
                    await drainer  # to the end of the log: the process has exited
            except TimeoutError:
                pass
        if failed:
            print(f"agentsdk serve {' '.join(args)}: the last of its log\n" + "".join(log[-100:]), file=sys.stderr)


async def _final_joints(behavior: str, backend: str, **options: Any) -> np.ndarray:
    module = load_behavior(behavior)
    async with agentsdk.connect(backend, robot="arm3", safety=SAFETY, **options) as robot:
        assert not robot.realtime
        await module.main(robot)
        await robot.clock.sleep(0.2)
        return np.array((await robot.read()).position)


@pytest.mark.slow
async def test_behaviors_end_in_the_same_joints_on_mujoco_and_over_ros2_in_lockstep() -> None:
    """Acceptance 1: patrol (a state machine of moves) and pick_place (trajectories) run unchanged."""
    did = _domain()
    async with _serve("--backend", "mujoco", "--lockstep", "--robot", "arm3", "--namespace", "/patrol",
                               "--robot", "arm3", "--namespace", "/pick", domain_id=did) as served:
        for behavior, ns in (("patrol", "/patrol"), ("pick_place", "/pick")):
            local = await _final_joints(behavior, "mujoco")
            remote = await _final_joints(behavior, "ros2", namespace=ns, domain_id=served.domain_id)
            assert np.abs(remote - local).max() <= 1e-3, (behavior, local, remote)
            # the behavior moved the robot: the comparison is not of two robots at rest where they started
            assert np.abs(local).max() > 0.1, (behavior, local)


async def test_description_and_time_model_come_from_the_robot() -> None:
    """No ``robot=``: the description from robot_description; no ``realtime=``: lockstep from its clock."""
    did = _domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=False, safety=SAFETY) as served, \
            expose(served, "/arm1", domain_id=did):
        async with agentsdk.connect("ros2", namespace="/arm1", domain_id=did, safety=SAFETY) as robot:
            assert robot.joint_names == served.joint_names
            assert [j.upper for j in robot.joints] == [j.upper for j in served.joints]
            assert not robot.realtime and robot.backend.interface == "agentsdk"  # type: ignore[attr-defined]
            t0 = served.clock.now()
            result = await robot.move_to({"joint1": 0.4}, duration=0.5)
            assert result.ok, result
            # lockstep: the served robot ran exactly as long as the client's robot time
            assert abs((served.clock.now() - t0) - robot.clock.now()) <= served.control_period + 1e-9
            assert abs(served.latest_state().position[0] - 0.4) < 1e-6


async def test_realtime_robot_and_stale_joint_states_fault_before_any_command() -> None:
    """A realtime served robot: joint_states drive the state; when they stop, the robot faults (stale_after)."""
    did = _domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety=SAFETY) as served:
        face = expose(served, "/rt", domain_id=did, rate=100.0)
        await face.start()
        try:
            async with agentsdk.connect("ros2", robot="arm3", namespace="/rt", domain_id=did, safety=SAFETY,
                                        stale_after=1.0) as robot:
                assert robot.realtime
                result = await robot.move_to({"joint2": 0.3}, duration=0.8)
                assert result.ok, result
                await asyncio.sleep(0.2)
                assert abs(served.latest_state().position[1] - 0.3) < 0.01
                backend = robot.backend
                await face.aclose()  # the robot's joint_states stop
                async with asyncio.timeout(5):
                    while robot.safety.state.name != "FAULT":  # noqa: ASYNC110 -- polls state another thread sets
                        await asyncio.sleep(0.01)
                cause = robot.safety.cause
                assert isinstance(cause, BackendFault) and "stale_after 1 s" in str(cause), cause
                # every write was on a state at most stale_after old, and none came after the bound
                assert 0.0 <= backend.last_write_age <= 1.0  # type: ignore[attr-defined]
                assert 0.0 <= backend.last_write - backend._last_rx <= 1.0  # type: ignore[attr-defined]
                with pytest.raises(SafetyFault):
                    await robot.command(JointCommand("position", {"joint2": 0.0}))
        finally:
            await face.aclose()


async def test_served_stream_applies_each_command_once_in_order() -> None:
    """The serving side: a repeated or older sequence number is dropped, a malformed one too."""
    did = _domain()
    async with agentsdk.connect("mock", robot="arm3", realtime=False, safety=SAFETY) as served, \
            expose(served, "/seq", domain_id=did) as face:
        loop = asyncio.get_running_loop()
        replies: list[str] = []
        node = DdsNode(did, "/seq", loop)
        try:
            node.subscribe(STATE_TOPIC, JointState, lambda m: replies.append(m.header.frame_id))
            writer = node.writer(COMMAND_TOPIC, JointState, QOS_STREAM)
            node.start()
            async with asyncio.timeout(10):
                while not writer.get_matched_subscriptions():  # noqa: ASYNC110 -- polls state another thread sets
                    await asyncio.sleep(0.02)
            session = "00000000deadbeef"

            def send(seq: int, q: float, frame: str | None = None) -> None:
                writer.write(JointState(Header(frame_id=frame or f"{session}:{seq:016x}"), ["joint1"], [q]))

            send(1, 0.1)
            send(3, 0.3)
            send(2, 0.2)  # older than 3: dropped
            send(3, 0.3)  # repeated: dropped
            send(0, 0.0, frame="no-sequence")
            send(4, 0.4)
            writer.write(JointState(Header(frame_id=f"{session}:{5:016x}")))  # a sync: answered with the state
            async with asyncio.timeout(10):
                while not replies:  # noqa: ASYNC110 -- polls state another thread sets
                    await asyncio.sleep(0.02)
            await asyncio.sleep(0.2)
            assert replies == [f"{session}:{5:016x}"]  # applied realtime commands are not answered
            assert face.stream.applied == 3 and face.stream.dropped == 3
            assert served.command_targets()[0] == pytest.approx(0.4)
        finally:
            node.close()


async def test_bad_options_and_no_robot_are_specific_errors() -> None:
    with pytest.raises(ConfigurationError, match="namespace"):
        async with agentsdk.connect("ros2", robot="arm3", realtime=True, namespace="/a b"):
            pass
    with pytest.raises(ConfigurationError, match="command_joints"):
        async with agentsdk.connect("ros2", robot="arm3", realtime=True, command_joints=("nope",)):
            pass
    with pytest.raises(BackendStartError, match="joint_states"):
        async with agentsdk.connect("ros2", robot="arm3", realtime=True, domain_id=_domain(), timeout=0.5):
            pass
    with pytest.raises(BackendStartError, match="robot_description"):
        async with agentsdk.connect("ros2", domain_id=_domain(), timeout=0.5):
            pass


# ------------------------------------------------------------ acceptance 2: a ros2_control JTC on Fast DDS
async def test_ros2_backend_drives_the_fast_dds_jtc_and_faults_when_its_joint_states_stop(
        domain: Domain, fastdds_peer: Path) -> None:
    """The Fast DDS peer plays a JTC (joint_states out, trajectories in); stopping its joint_states faults
    the robot within ``stale_after``, the controller gets a hold, and nothing is streamed on stale state."""
    import signal

    stale_after = 0.5
    proc = await asyncio.create_subprocess_exec(
        str(fastdds_peer), "jtc", "/ur", "60", "joint1=0.1", "joint2=0.0", "joint3=-0.1", env=domain.env,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    assert proc.stdout is not None
    lines: list[str] = []

    async def read_lines() -> None:
        assert proc.stdout is not None
        while line := (await proc.stdout.readline()).decode():
            lines.append(line.strip())

    reader = asyncio.create_task(read_lines())
    try:
        # no robot=, no realtime=: a plain ros2_control robot has no clock -> realtime, no agentsdk stream -> JTC
        async with agentsdk.connect("ros2", robot="arm3", namespace="/ur", domain_id=domain.id, safety=SAFETY,
                                    stale_after=stale_after, timeout=30.0) as robot:
            backend: Any = robot.backend
            assert robot.realtime and backend.interface == "joint_trajectory"
            assert not backend.goals_available  # no action server in rmw_cyclonedds' format: streamed
            start = (await robot.read()).position
            assert start.tolist() == pytest.approx([0.1, 0.0, -0.1], abs=1e-9)
            result = await robot.move_to({"joint1": 0.5, "joint3": 0.2}, duration=1.5)
            assert result.ok, result
            await asyncio.sleep(0.3)
            q = (await robot.read()).position
            assert q.tolist() == pytest.approx([0.5, 0.0, 0.2], abs=0.01)
            proc.send_signal(signal.SIGUSR1)  # the controller's joint_states stop
            async with asyncio.timeout(10):
                while robot.safety.state.name != "FAULT":  # noqa: ASYNC110 -- polls state the loop sets
                    await asyncio.sleep(0.01)
            cause = robot.safety.cause
            assert isinstance(cause, BackendFault) and "stale_after 0.5" in str(cause), cause
            age = float(str(cause).split(" are ")[1].split(" s old")[0])
            # detected at the first tick past the bound (the message rounds the age to 1 ms)
            assert stale_after <= age <= stale_after + 0.25, cause
            assert 0.0 <= backend.last_write_age <= stale_after
            assert 0.0 <= backend.last_write - backend._last_rx <= stale_after
            async with asyncio.timeout(10):
                while not any(line.startswith("HOLD") for line in lines):  # noqa: ASYNC110 -- the reader fills it
                    await asyncio.sleep(0.02)
            stopped = next(float(line.split()[1]) for line in lines if line.startswith("STOPPED"))
            hold = next(float(line.split()[1]) for line in lines if line.startswith("HOLD"))
            assert hold >= stopped
    finally:
        await _stop(proc)
        await reader


# ------------------------------------------------------------ e-stop and recovery against a JTC
async def test_estop_holds_the_controller_cancels_its_goals_and_a_stale_fault_recovers() -> None:
    """A JTC played in-process: an e-stop sends a hold (empty trajectory) and a cancel of every goal, then
    nothing is streamed while torque is off; stale joint_states fault, fresh ones let reset() recover."""
    did = _domain()
    loop = asyncio.get_running_loop()
    trajs: list[JointTrajectory] = []
    cancels: list[CancelGoal_Request] = []

    def on_cancel(_h: Any, req: CancelGoal_Request, reply: Any) -> None:
        cancels.append(req)
        reply(CancelGoal_Response())

    node = DdsNode(did, "/fake", loop)
    node.subscribe("joint_trajectory_controller/joint_trajectory", JointTrajectory, trajs.append)
    node.service("joint_trajectory_controller/follow_joint_trajectory/_action/cancel_goal", CancelGoal_Request,
                 CancelGoal_Response, on_cancel)
    js = node.writer("joint_states", JointState)
    node.start()
    publishing = [True]

    async def publish() -> None:
        while True:
            if publishing[0]:
                js.write(JointState(Header(), ["joint1", "joint2", "joint3"], [0.1, 0.2, 0.3]))
            await asyncio.sleep(0.01)

    async def until(predicate: Any) -> None:
        async with asyncio.timeout(10):
            while not predicate():  # noqa: ASYNC110 -- DDS callbacks and the control loop change it
                await asyncio.sleep(0.01)

    task = asyncio.create_task(publish())
    try:
        async with agentsdk.connect("ros2", robot="arm3", namespace="/fake", domain_id=did, realtime=True,
                                    stale_after=0.5, safety=SAFETY) as robot:
            backend: Any = robot.backend
            assert backend.interface == "joint_trajectory"
            assert (await robot.read()).position.tolist() == [0.1, 0.2, 0.3]
            await until(lambda: len(trajs) > 5)
            assert all(len(t.points) == 1 and list(t.joint_names) == ["joint1", "joint2", "joint3"] for t in trajs)
            assert list(trajs[-1].points[0].positions) == pytest.approx([0.1, 0.2, 0.3])  # holding where it is
            await robot.estop(0)
            await until(lambda: any(not t.points for t in trajs) and cancels)
            assert bytes(cancels[-1].goal_info.goal_id.uuid) == bytes(16)  # zero id, zero stamp: every goal
            count = len(trajs)
            await asyncio.sleep(0.2)
            assert len(trajs) == count  # torque off: nothing streamed
            await robot.reset()
            await robot.enable()
            await until(lambda: len(trajs) > count + 5)
            publishing[0] = False
            await until(lambda: robot.safety.state.name == "FAULT")
            assert "stale_after 0.5" in str(robot.safety.cause)
            with pytest.raises(BackendFault, match="cannot recover"):
                await robot.reset()
            publishing[0] = True
            await asyncio.sleep(0.2)
            await robot.reset()
            await robot.enable()
            assert robot.safety.state.name == "OK"
            count = len(trajs)
            await until(lambda: len(trajs) > count + 5)  # streaming again
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        node.close()
