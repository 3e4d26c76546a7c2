"""Leader-follower teleoperation between two robots of any backends.

``agentsdk teleop --leader mock:arm3 --follower mujoco:arm3`` (or :func:`follow_leader` from
Python) streams the leader's measured joint positions to the follower as position commands,
every follower control period:

* **mapping**: joints are matched by name; when the two robots share no joint name, by order
  (the first joints of each);
* **scaling**: ``scale`` multiplies the leader's motion from where the session started
  (``q_f = q_f0 + scale * (q_l - q_l0)``);
* **limits**: every command goes through the follower's ``robot.command`` and so through its
  safety layer (position limits, the per-cycle step limit, e-stops); the target is also clipped
  into the follower's joint limits first;
* **alignment**: the follower first moves (``move_to``, within its limits) to the leader's pose,
  so the session never starts with a jump;
* **dead-man rule**: when the leader's state stops arriving (its stamp does not advance for
  ``stale_timeout`` seconds of follower time: a leader that stopped streaming, was unplugged or
  closed), the follower holds where it is (release = hold) and the session ends.

The session ends when ``duration`` elapsed, when the leader goes stale, or when cancelled.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import AgentSDKError, ConfigurationError, InvalidValueError, RobotClosedError
from .types import JointCommand

if TYPE_CHECKING:
    from .robot import Robot

__all__ = ["TeleopReport", "follow_leader", "joint_map", "parse_endpoint"]


@dataclass(frozen=True)
class TeleopReport:
    """What a session did."""

    #: (leader joint, follower joint) pairs
    pairs: tuple[tuple[str, str], ...]
    #: follower control periods a command was sent
    commands: int
    #: largest |follower target - follower measured| seen while streaming (rad or m), after alignment
    max_tracking_error: float
    #: why it ended: "duration", "leader stopped" or "cancelled"
    ended: str


def parse_endpoint(text: str, what: str) -> tuple[str, str]:
    """``BACKEND:ROBOT`` -> ``(backend, robot)`` (the robot may be a path containing ':')."""
    backend, sep, robot = text.partition(":")
    if not sep or not backend or not robot:
        raise ConfigurationError(f"--{what} expects BACKEND:ROBOT (e.g. mujoco:arm3), got {text!r}")
    return backend, robot


def joint_map(leader: Robot, follower: Robot) -> tuple[tuple[str, str], ...]:
    """The joints to couple: by name where both robots have them, else by order."""
    shared = [n for n in leader.joint_names if n in follower.joint_names]
    if shared:
        return tuple((n, n) for n in shared)
    return tuple(zip(leader.joint_names, follower.joint_names, strict=False))


async def follow_leader(
    leader: Robot,
    follower: Robot,
    *,
    scale: float = 1.0,
    duration: float | None = None,
    stale_timeout: float = 0.1,
) -> TeleopReport:
    """Make ``follower`` follow ``leader`` (see the module documentation); returns a :class:`TeleopReport`."""
    if not (np.isfinite(scale) and scale > 0):
        raise InvalidValueError(f"scale must be a positive number, got {scale!r}")
    if not stale_timeout > 0:
        raise InvalidValueError(f"stale_timeout must be > 0 s, got {stale_timeout!r}")
    pairs = joint_map(leader, follower)
    if not pairs:
        raise ConfigurationError(f"{leader.name} and {follower.name} have no joints to couple")
    li = np.array([leader.joint_names.index(a) for a, _ in pairs], dtype=np.intp)
    fi = np.array([follower.joint_names.index(b) for _, b in pairs], dtype=np.intp)
    names = tuple(b for _, b in pairs)
    lo = np.array([follower.joints[i].lower for i in fi])
    hi = np.array([follower.joints[i].upper for i in fi])

    first = leader.latest_state()
    q_l0 = np.array(first.position)[li]
    q_f0 = np.array(follower.latest_state().position)[fi] if scale != 1.0 else q_l0
    # align: move the follower to where the leader is (within its limits), then stream
    start = np.clip(q_f0, lo, hi)
    aligned = await follower.move_to(dict(zip(names, start.tolist(), strict=True)))
    if not aligned.ok:
        raise AgentSDKError(f"teleop: the follower could not reach the leader's pose: {aligned.message}")

    clock = follower.clock
    period = follower.control_period
    t_end = None if duration is None else clock.now() + duration
    last_stamp, last_fresh = leader.latest_state().stamp, clock.now()
    commands, worst, ended = 0, 0.0, "cancelled"
    sent = start  # the last target sent: the follower's measured position is compared with it
    try:
        while True:
            now = clock.now()
            if t_end is not None and now >= t_end:
                ended = "duration"
                break
            try:
                st = leader.latest_state()
            except RobotClosedError:
                ended = "leader stopped"  # dead-man: the leader is gone -> hold where we are
                break
            if st.stamp != last_stamp:
                last_stamp, last_fresh = st.stamp, now
            elif now - last_fresh > stale_timeout:
                ended = "leader stopped"  # dead-man: no fresh leader state -> hold where we are
                break
            q_l = np.array(st.position)[li]
            target = np.clip(q_f0 + scale * (q_l - q_l0), lo, hi)
            measured = np.array(follower.latest_state().position)[fi]
            worst = max(worst, float(np.max(np.abs(sent - measured))))
            await follower.command(JointCommand("position", dict(zip(names, target.tolist(), strict=True))))
            sent = target
            commands += 1
            await clock.sleep(period)
    finally:
        if not follower.closed and follower.safety.state.name in ("OK", "HOLD"):
            held = np.array(follower.latest_state().position)[fi]
            try:  # release = hold: the follower stays where it is
                await asyncio.shield(follower.command(JointCommand("position", dict(
                    zip(names, held.tolist(), strict=True)))))
            except AgentSDKError:
                pass
    return TeleopReport(pairs, commands, worst, ended)
