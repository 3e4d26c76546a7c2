"""The web view without a browser: it publishes snapshots, its e-stop latches the configured category,
reset/enable go through the robot, it binds 127.0.0.1 only, and a taken port is a clear error."""

from __future__ import annotations

import asyncio
import importlib.util
import socket
from collections.abc import Callable

import pytest

import agentsdk
from agentsdk.errors import ConfigurationError

pytestmark = [pytest.mark.timeout(300),
              pytest.mark.skipif(importlib.util.find_spec("viser") is None, reason="needs agentsdk[web] (viser)")]

SAFETY = {"stall_timeout": 5.0, "ui_stop_category": 2}


async def _until(pred: Callable[[], bool]) -> None:
    """Poll a condition another thread makes true (the view's publisher), for at most 120 s."""
    async with asyncio.timeout(120.0):
        while not pred():  # noqa: ASYNC110  (set by a thread: no event to wait on)
            await asyncio.sleep(0.05)


async def test_snapshots_estop_and_recovery() -> None:
    from agentsdk.webview import HOST, WebView

    WebView.prepare()
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY, realtime=True) as robot:
        view = WebView.attach(robot, port=0)
        try:
            await _until(view.ready.is_set)
            assert view.error is None and view.url.startswith(f"http://{HOST}:") and view.port > 0
            assert view.stop_category == 2
            await robot.move_to({"joint1": 0.3}, duration=0.5)
            await _until(lambda: view.last is not None and abs(view.last.position[0] - 0.3) < 0.01)
            assert view.last is not None and view.last.safety == "OK"
            view.estop()
            await _until(lambda: view.last is not None and view.last.safety == "ESTOP")
            assert "category 2" in view.last.cause
            view.request("reset")
            await _until(lambda: robot.safety.state.name == "DISABLED")
            view.request("enable")
            await _until(lambda: robot.safety.state.name == "OK")
        finally:
            view.close()
        view.close()  # idempotent


async def test_a_taken_port_is_refused() -> None:
    from agentsdk.webview import WebView

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        async with agentsdk.connect("mock", robot="arm3", safety=SAFETY) as robot:
            with pytest.raises(ConfigurationError, match=rf"127.0.0.1:{port}.*choose another --port"):
                WebView.attach(robot, port=port)


@pytest.mark.parametrize("robot_name", ["ur5", "panda"])
async def test_a_cartesian_jog_moves_the_end_effector_one_centimetre(robot_name: str) -> None:
    """What a W key press (or the +x button) on the page does: +1 cm in x within 1 mm, on MuJoCo."""
    import numpy as np

    from agentsdk.arm import ready_configuration
    from agentsdk.description.catalog import find_robot
    from agentsdk.webview import JOG_STEP, WebView

    if find_robot(robot_name) is None:
        pytest.skip(f"{robot_name} is not installed")
    WebView.prepare()
    async with agentsdk.connect("mujoco", robot=robot_name, safety=SAFETY) as robot:
        view = WebView.attach(robot, port=0)
        try:
            await _until(view.ready.is_set)
            link = view._jog_link
            # away from the start pose's singularity (both start stretched out)
            q = ready_configuration(robot.kinematics, link, robot.latest_state().position, full=True)
            await robot.move_to(dict(zip(robot.joint_names, q.tolist(), strict=True)))
            await robot.clock.sleep(0.5)
            before = robot.kinematics.fk(link).position.copy()
            view.jog_cartesian(0, JOG_STEP)
            assert view._jogging is not None
            await asyncio.wrap_future(view._jogging)
            await robot.clock.sleep(1.0)  # settle
            moved = robot.kinematics.fk(link).position - before
            assert abs(moved[0] - 0.01) < 1e-3 and np.linalg.norm(moved[1:]) < 1e-3, moved
            # a press while a jog runs is dropped, not queued: release = no further motion
            view.jog_cartesian(0, JOG_STEP)
            first = view._jogging
            view.jog_cartesian(0, JOG_STEP)
            assert view._jogging is first
            await asyncio.wrap_future(first)
        finally:
            view.close()


async def test_stopping_a_jog_holds_the_arm() -> None:
    """What Space does on the page: the running step is cancelled, the arm decelerates and holds short of it."""
    import numpy as np

    from agentsdk.webview import WebView

    WebView.prepare()
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY, realtime=True) as robot:
        view = WebView.attach(robot, port=0)
        try:
            await _until(view.ready.is_set)
            view.jog_joint("joint1", 1.0)  # a long step
            await _until(lambda: abs(robot.latest_state().position[0]) > 0.05)
            view.stop_jog()
            await _until(lambda: view._jogging is not None and view._jogging.done())
            stopped_at = robot.latest_state().position[0]
            for _ in range(100):  # the stop ramp: within the joint's acceleration and jerk limits
                await robot.clock.sleep(0.05)
                if float(np.max(np.abs(robot.latest_state().velocity))) < 1e-3:
                    break
            st = robot.latest_state()
            assert float(np.max(np.abs(st.velocity))) < 1e-3 and stopped_at <= st.position[0] < 0.9, (stopped_at, st)
            await robot.clock.sleep(0.5)
            assert abs(robot.latest_state().position[0] - st.position[0]) < 1e-4  # and holds
            view.stop_jog()  # nothing running: nothing happens
        finally:
            view.close()
