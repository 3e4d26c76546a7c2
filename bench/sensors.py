"""Sensor benchmarks: a MuJoCo camera sensor's cost per frame in lockstep vs MuJoCo's own ``mujoco.Renderer``.

The SDK figure is end to end: the wall time per control tick of a lockstep robot whose 320×240
camera renders every tick, minus the time per tick of the same robot without the camera (same
run, same other sensors). The baseline is ``mujoco.Renderer`` rendering the same compiled model
from the same camera (``update_scene`` + ``render``; a second render for depth, which the SDK
reads from the same render). A third row shows what the other sensors (IMU, F/T, contact, range,
joint) cost per tick next to the same robot with no sensor declared (which registers no sensor
hook at all: a robot without sensors pays nothing for the feature).

Offscreen OpenGL: ``MUJOCO_GL=egl`` (or ``osmesa``) must be set for ``mujoco.Renderer``.
"""

from __future__ import annotations

import asyncio
import os
import re
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from agentsdk.bench.common import Comparison, Section, progress

__all__ = ["run"]

ROOT = Path(__file__).resolve().parent.parent
FIXTURE = ROOT / "tests" / "fixtures" / "sensor_arm"


def _config(directory: Path, camera: dict[str, Any] | None, *, bare: bool = False) -> Path:
    """sensor_arm's robot.yaml with the given camera (none: no camera); ``bare``: no sensors declared anywhere."""
    data = yaml.safe_load((FIXTURE / "robot.yaml").read_text())
    data["description"] = str(FIXTURE / "sensor_arm.urdf")
    data["sensors"] = [s for s in data["sensors"] if s["type"] != "camera"]
    if bare:
        urdf = (FIXTURE / "sensor_arm.urdf").read_text()
        for tag in ("gazebo", "ros2_control"):
            urdf = re.sub(rf"<{tag}\b.*?</{tag}>", "", urdf, flags=re.DOTALL)
        (directory / "bare.urdf").write_text(urdf)
        data["description"] = str(directory / "bare.urdf")
        data["sensors"] = []
        path = directory / "robot_bare.yaml"
        path.write_text(yaml.safe_dump(data))
        return path
    if camera is not None:
        data["sensors"].append({
            "name": "cam", "type": "camera", "link": "world", "xyz": [0.6, 0.0, 1.0],
            "rpy": [0.0, 1.5707963267948966, 0.0], "rate": float(data["update_rate"]), "camera": camera,
        })
    path = directory / f"robot_{'cam' if camera else 'nocam'}_{bool(camera and camera.get('depth'))}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


async def _per_tick(path: Path, ticks: int) -> tuple[float, Any]:
    import agentsdk

    async with agentsdk.connect("mujoco", path, safety={"stall_timeout": None}) as robot:
        if "cam" in robot.sensors:
            robot.sensors.read("cam")  # a camera renders in the tick once it has been read
        await robot.clock.sleep(5 * robot.control_period)  # warm
        t0 = time.perf_counter()
        await robot.clock.sleep(ticks * robot.control_period)
        per = (time.perf_counter() - t0) / ticks
        return per, robot.backend


def _renderer_per_frame(model: Any, data: Any, cam: int, frames: int, depth: bool) -> float:
    import mujoco

    r = mujoco.Renderer(model, 240, 320)
    try:
        for _ in range(3):  # warm (shader compilation)
            r.update_scene(data, camera=cam)
            r.render()
        t0 = time.perf_counter()
        for _ in range(frames):
            r.update_scene(data, camera=cam)
            r.render()
            if depth:
                r.enable_depth_rendering()
                r.render()
                r.disable_depth_rendering()
        return (time.perf_counter() - t0) / frames
    finally:
        r.close()


def run(quick: bool = False) -> Section:
    """The camera's cost per frame vs ``mujoco.Renderer``, and the other sensors' cost per tick."""
    import mujoco

    sec = Section("sensors", "MuJoCo camera sensor per frame vs mujoco.Renderer; sensors' cost per tick")
    frames = 20 if quick else 60
    ticks = 500 if quick else 2000
    os.environ.setdefault("MUJOCO_GL", "egl")
    with tempfile.TemporaryDirectory(prefix="agentsdk-bench-sensors-") as tmp:
        d = Path(tmp)
        plain, _ = asyncio.run(_per_tick(_config(d, None), frames))
        for depth in (False, True):
            progress(f"sensors: camera depth={depth}")
            cam_cfg = {"width": 320, "height": 240, "horizontal_fov": 0.6, "depth": depth}
            with_cam, backend = asyncio.run(_per_tick(_config(d, cam_cfg), frames))
            model = backend.model
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
            cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "agentsdk/cam")
            try:
                base = _renderer_per_frame(model, data, cid, frames, depth)
            except Exception as exc:  # no GL for mujoco.Renderer here
                sec.notes.append(f"mujoco.Renderer unavailable ({exc}); set MUJOCO_GL=egl or osmesa")
                base = None
            what = "rgb + depth" if depth else "rgb"
            sec.comparisons.append(Comparison(
                f"sensor_arm mujoco: 320x240 camera ({what}) per frame in lockstep", "ms",
                baseline=None if base is None else base * 1e3, sdk=(with_cam - plain) * 1e3,
                baseline_label="mujoco.Renderer", ratio_target=1.2,
                note="SDK: tick time with the camera rendering every tick minus without it (same run)",
            ))
        progress("sensors: other sensors per tick")
        none, _ = asyncio.run(_per_tick(_config(d, None, bare=True), ticks))
        some, _ = asyncio.run(_per_tick(_config(d, None), ticks))
        sec.comparisons.append(Comparison(
            "sensor_arm mujoco: lockstep tick with 5 sensors (F/T, contact, IMU, range, joint)", "µs",
            baseline=none * 1e6, sdk=some * 1e6, baseline_label="same robot, no sensors declared",
        ))
    return sec
