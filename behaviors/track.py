"""Track: a fixed-rate feedback agent following a moving target (a sine on joint1).

    agentsdk run behaviors/track.py                          # MuJoCo, lockstep (simulated time)
    agentsdk run behaviors/track.py --backend mock --realtime   # wall clock: see the timing stats

Every period the agent reads the state, computes the target and sends a position
command with velocity feed-forward (through ``robot.command``, so the safety
layer applies). The amplitude fades in over RAMP seconds so the arm starts
without a jump. At the end it prints the tracking error and the loop's timing
statistics (:class:`agentsdk.feedback.LoopStats`).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from agentsdk import JointCommand, JointState, Robot
from agentsdk.errors import ConfigurationError
from agentsdk.feedback import FeedbackAgent

ROBOT = "arm3"

JOINT = "joint1"
AMPLITUDE = 0.6  # rad
FREQUENCY = 0.5  # Hz
RAMP = 1.0  # s: amplitude fade-in
DURATION = 4.0  # s of robot time

log = logging.getLogger("behaviors.track")


class SineTracker(FeedbackAgent):
    """Position + velocity feed-forward on ``joint``: q*(t) = center + e(t) * A * sin(2 pi f t)."""

    def __init__(self, joint: str = JOINT, amplitude: float = AMPLITUDE, frequency: float = FREQUENCY) -> None:
        self.joint = joint
        self.amplitude = amplitude
        self.omega = 2 * math.pi * frequency
        self.errors: list[float] = []

    async def setup(self, robot: Robot) -> None:
        if self.joint not in robot.joint_names:
            raise ConfigurationError(f"track: robot {robot.name!r} has no joint {self.joint!r}")
        state = await robot.read()
        self.j = state.index(self.joint)
        self.center = float(state.position[self.j])
        self.t0 = state.stamp
        self.last_target: float | None = None

    def target(self, t: float) -> tuple[float, float]:
        """Target position and velocity at ``t`` seconds after the start."""
        s = min(1.0, t / RAMP)
        env = s * s * (3 - 2 * s)  # smoothstep fade-in
        denv = 6 * s * (1 - s) / RAMP if t < RAMP else 0.0
        a, w = self.amplitude, self.omega
        q = self.center + env * a * math.sin(w * t)
        v = denv * a * math.sin(w * t) + env * a * w * math.cos(w * t)
        return q, v

    async def update(self, state: JointState) -> JointCommand:
        if self.last_target is not None:  # how well the last period's target was reached
            self.errors.append(self.last_target - float(state.position[self.j]))
        q, v = self.target(state.stamp - self.t0)
        self.last_target = q
        return JointCommand("position", {self.joint: q}, velocity={self.joint: v})


async def main(robot: Robot) -> None:
    agent = SineTracker()
    rate = 1.0 / robot.control_period  # one update per control tick (valid in lockstep too)
    print(
        f"track: sine {AMPLITUDE:g} rad at {FREQUENCY:g} Hz on {JOINT} of {robot.name} ({robot.backend}), "
        f"{rate:g} Hz for {DURATION:g} s ({'realtime' if robot.realtime else 'lockstep'})"
    )
    stats = await agent.run(robot, rate=rate, duration=DURATION)
    err = np.abs(np.array(agent.errors))
    print(
        f"tracking error (target of the previous period - measured): RMS {math.sqrt(np.mean(err**2)):.4f} rad, "
        f"max {err.max():.4f} rad"
    )
    print(f"timing: {stats.summary()}")
    log.info("loop stats %s", stats.as_dict())
    if stats.count == 0:
        raise RuntimeError("track: the feedback loop never ran")
