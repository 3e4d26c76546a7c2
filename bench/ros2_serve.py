"""Cost of serving a robot on ROS 2 (issue 22 acceptance 5), against baselines from the same run.

* Lockstep speed: arm3 on MuJoCo follows a trajectory through random waypoints for a fixed
  span of robot time, unserved vs served with ``joint_states`` at the control rate (500 Hz)
  while a subscriber in another process takes them (target: at most 10 % slower).
* Tick -> peer latency: a realtime arm3 served at the control rate; a subscriber process
  (cyclonedds-python, a waitset, no polling) records ``receive time - header.stamp`` for every
  sample. Baseline: a raw cyclonedds-python publisher writing the same ``JointState`` message
  (stamped at write time) at the same rate to the same kind of subscriber.

Everything stays on 127.0.0.1 (the loopback Cyclone DDS configuration), on a random domain.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import subprocess
import sys
import textwrap
import time
from typing import Any

import numpy as np

import agentsdk
from agentsdk.bench.common import Comparison, Section, median, progress

_SUBSCRIBER = textwrap.dedent("""
    import json, sys, time
    from cyclonedds.core import ReadCondition, SampleState, ViewState, InstanceState, WaitSet
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
    from agentsdk.ros2.dds import QOS_DEFAULT, loopback_config
    from agentsdk.ros2.msgs import JointState
    did, topic, seconds = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    dom = Domain(did, loopback_config(did))
    dp = DomainParticipant(did)
    rd = DataReader(dp, Topic(dp, topic, JointState), qos=QOS_DEFAULT)
    ws = WaitSet(dp)
    ws.attach(ReadCondition(rd, SampleState.Any | ViewState.Any | InstanceState.Any))
    print("ready", flush=True)
    lat, end = [], None
    while end is None or time.time() < end:
        ws.wait(duration(milliseconds=100))
        now = time.time()
        for s in rd.take(N=256):
            if isinstance(s, JointState):
                if end is None:
                    end = now + seconds
                lat.append(now - (s.header.stamp.sec + s.header.stamp.nanosec * 1e-9))
    print(json.dumps(lat), flush=True)
""")


def _domain() -> int:
    """A random domain of this run's own; within ``AGENTSDK_TEST_DOMAINS=lo-hi`` when the test suite runs it
    (each parallel test worker has its own share there, so no other test's participants meet this one's)."""
    low, high = 30, 230
    if bounds := os.environ.get("AGENTSDK_TEST_DOMAINS"):
        low, high = (int(x) for x in bounds.split("-"))
    return random.SystemRandom().randint(low, high)


def _subscriber(domain: int, topic: str, seconds: float) -> subprocess.Popen[str]:
    env = dict(os.environ)
    env.pop("CYCLONEDDS_URI", None)
    proc = subprocess.Popen([sys.executable, "-c", _SUBSCRIBER, str(domain), topic, str(seconds)],
                            stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    proc.stdout.readline()  # "ready"
    return proc


def _latencies(proc: subprocess.Popen[str]) -> np.ndarray:
    out, _ = proc.communicate(timeout=120)
    lines = [line for line in out.splitlines() if line.startswith("[")]
    return np.array(json.loads(lines[-1]) if lines else [])


async def _lockstep_run(sim_seconds: float, serve: bool, domain: int) -> tuple[float, int]:
    from agentsdk.ros2 import expose

    rng = np.random.default_rng(1)
    async with agentsdk.connect("mujoco", robot="arm3") as robot:
        face = expose(robot, "bench", domain_id=domain, rate=1.0 / robot.control_period) if serve else None
        if face is not None:
            await face.start()
            await asyncio.sleep(1.0)  # discovery: the subscriber matches before timing starts
        try:
            t0, wall = robot.clock.now(), time.perf_counter()
            while robot.clock.now() - t0 < sim_seconds:
                target = {n: float(rng.uniform(-0.8, 0.8)) for n in robot.joint_names}
                await robot.move_to(target)
            wall = time.perf_counter() - wall
        finally:
            if face is not None:
                await face.aclose()
        return wall, 0 if face is None else face.published


async def _served_latency(seconds: float, domain: int) -> None:
    from agentsdk.ros2 import expose

    async with (
        agentsdk.connect("mujoco", robot="arm3", realtime=True) as robot,
        expose(robot, "bench", domain_id=domain, rate=1.0 / robot.control_period),
    ):
        end = time.monotonic() + seconds
        rng = np.random.default_rng(2)
        while time.monotonic() < end:
            await robot.move_to({n: float(rng.uniform(-0.8, 0.8)) for n in robot.joint_names})


def _raw_latency(seconds: float, domain: int, rate: float, names: list[str]) -> None:
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic

    from agentsdk.ros2.dds import QOS_DEFAULT, loopback_config
    from agentsdk.ros2.msgs import Header, JointState, Time

    dom = Domain(domain, loopback_config(domain))
    dp = DomainParticipant(domain)
    w = DataWriter(dp, Topic(dp, "rt/raw/joint_states", JointState), qos=QOS_DEFAULT)
    time.sleep(1.0)
    n = len(names)
    end = time.monotonic() + seconds + 0.5
    nxt = time.monotonic()
    while time.monotonic() < end:
        w.write(JointState(Header(Time.from_seconds(time.time())), names, [0.1] * n, [0.0] * n, [0.0] * n))
        nxt += 1.0 / rate
        time.sleep(max(0.0, nxt - time.monotonic()))
    del w, dp, dom


def run(quick: bool = False) -> Section:
    """Lockstep speed served vs unserved, and tick -> peer latency vs raw cyclonedds pub/sub."""
    sec = Section("ros2_serve", "serving joint_states on ROS 2 (DDS): lockstep cost and tick -> peer latency")
    sim = 4.0 if quick else 15.0  # (4 s of lockstep robot time: ~0.05 s of wall time)
    lat_s = 1.0 if quick else 8.0  # quick: ~500 samples per latency figure

    # A/B interleaved, a subscriber process alive in both (on a small machine its CPU is not free)
    walls: dict[bool, list[float]] = {False: [], True: []}
    published = 0
    for rep in range(2 if quick else 3):
        for serve in (False, True):
            progress(f"ros2_serve: lockstep {'served at the control rate' if serve else 'unserved'} ({rep + 1})")
            domain = _domain()
            sub = _subscriber(domain, "rt/bench/joint_states", 1e9)
            try:
                wall, n = asyncio.run(_lockstep_run(sim, serve, domain))
            finally:
                sub.kill()
                sub.wait()
            walls[serve].append(wall)
            published += n
    sec.comparisons.append(Comparison(
        f"arm3 lockstep, {sim:g} s robot time, joint_states at 500 Hz to a subscriber process", "s wall",
        baseline=median(walls[False]), sdk=median(walls[True]), baseline_label="unserved", sdk_label="served",
        ratio_target=1.10,
        note=f"median of {len(walls[True])} interleaved runs each; {published} samples written (the publisher "
        "writes the newest sample at most 500 times per wall second)"))

    progress("ros2_serve: tick -> peer latency (served, realtime)")
    domain = _domain()
    sub = _subscriber(domain, "rt/bench/joint_states", lat_s)
    asyncio.run(_served_latency(lat_s + 1.5, domain))
    served = _latencies(sub)
    progress("ros2_serve: raw cyclonedds pub/sub latency")
    domain = _domain()
    sub = _subscriber(domain, "rt/raw/joint_states", lat_s)
    _raw_latency(lat_s, domain, 500.0, ["joint1", "joint2", "joint3"])
    raw = _latencies(sub)
    for q, label in ((50, "p50"), (99, "p99")):
        if len(served) and len(raw):
            sec.comparisons.append(Comparison(
                f"tick -> peer latency {label} (500 Hz, loopback)", "ms",
                baseline=float(np.percentile(raw, q) * 1e3), sdk=float(np.percentile(served, q) * 1e3),
                baseline_label="raw cyclonedds pub/sub", sdk_label="served robot"))
    data: dict[str, Any] = {"served_samples": len(served), "raw_samples": len(raw)}
    sec.data.update(data)
    sec.notes.append("latency = subscriber receive time - header.stamp (the tick's time for the served robot, "
                     "the write time for the raw publisher)")
    return sec


if __name__ == "__main__":
    print(run("--quick" in sys.argv).render())
