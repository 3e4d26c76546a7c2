"""Tracking in motion: how far the hand leaves a straight line, with and without the inverse-dynamics feed-forward.

Problem: example-robot-data's Panda (Franka "ready" pose) and UR5 with the defaults (model gains,
gravity compensation), a 10 cm sideways ``move_to_pose(..., linear=True)`` at full speed, in
lockstep; the figure is the largest distance of the hand from the line (FK of the measured
joints, every control period). Baseline, from the same run: the same motion with
``inverse_dynamics=False`` (gravity compensation only). Both are deterministic (lockstep), so
``--quick`` runs the same motions.
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from agentsdk.bench.common import Comparison, Section, Table, fmt, progress

#: the arm, its hand link and a non-singular start pose
ARMS: dict[str, tuple[str, str, dict[str, float]]] = {
    "panda": ("panda_description/urdf/panda.urdf", "panda_hand_tcp",
              {"panda_joint2": -0.785398, "panda_joint4": -2.35619, "panda_joint6": 1.5707,
               "panda_joint7": 0.785398, "panda_finger_joint1": 0.02}),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", "tool0",
            {"shoulder_lift_joint": -1.2, "elbow_joint": 1.5, "wrist_1_joint": -1.9, "wrist_2_joint": -1.57}),
}
OFFSET = (0.0, -0.1, 0.0)  # m: 10 cm sideways
LINE_TARGET = 2e-3  # m


def _corpus() -> Path:
    dist = importlib.metadata.distribution("example-robot-data")
    return Path(str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")))


async def _deviation(robot_yaml: str, backend: str, link: str, inverse_dynamics: bool) -> tuple[float, float]:
    import agentsdk
    from agentsdk import Pose

    async with agentsdk.connect(backend, robot=robot_yaml, inverse_dynamics=inverse_dynamics,
                                safety={"stall_timeout": 10.0}) as robot:
        kin = robot.kinematics
        await robot.clock.sleep(0.2)
        start = kin.fk(link)
        a = start.position.copy()
        b = a + np.asarray(OFFSET)
        ab = b - a
        worst = [0.0]

        async def watch() -> None:
            while True:
                p = kin.fk(link).position
                s = float(np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0))
                worst[0] = max(worst[0], float(np.linalg.norm(p - (a + s * ab))))
                await robot.clock.sleep(robot.control_period)

        task = asyncio.create_task(watch())
        t0 = robot.clock.now()
        try:
            result = await robot.move_to_pose(link, Pose(b, start.orientation), linear=True)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        if not result.ok:
            raise RuntimeError(f"the line did not complete: {result}")
        return worst[0], robot.clock.now() - t0


def run(quick: bool = False) -> Section:
    sec = Section("tracking", "tracking in motion: a 10 cm linear move_to_pose, hand distance from the line")
    try:
        root = _corpus()
    except importlib.metadata.PackageNotFoundError:
        sec.status = "skipped"
        sec.notes.append("example-robot-data is not installed (pip install -e '.[test]')")
        return sec
    rows: list[list[Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for arm, (urdf, link, start) in ARMS.items():
            q0 = ", ".join(f"{k}: {v}" for k, v in start.items())
            yaml = Path(tmp) / f"{arm}.yaml"
            yaml.write_text(f"description: {root / urdf}\ninitial_positions: {{{q0}}}\n", encoding="utf-8")
            for backend in ("mujoco", "pybullet"):
                progress(f"tracking: {arm} on {backend}, with and without the feed-forward")
                without, seconds = asyncio.run(_deviation(str(yaml), backend, link, False))
                with_ff, _ = asyncio.run(_deviation(str(yaml), backend, link, True))
                sec.comparisons.append(Comparison(
                    f"{arm} on {backend}: hand off the line", "mm", without * 1e3, with_ff * 1e3,
                    baseline_label="g(q) only", sdk_label="inverse dynamics", sdk_target=LINE_TARGET * 1e3,
                ))
                rows.append([arm, backend, fmt(seconds), fmt(without * 1e3), fmt(with_ff * 1e3)])
    sec.tables.append(Table("10 cm sideways line at full speed (lockstep)",
                            ("arm", "backend", "motion s", "g(q) only mm", "with inverse dynamics mm"), rows))
    return sec
