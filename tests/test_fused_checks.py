"""The safety layer's fused tick of the built-in checks (measured-position limits, following error) against
the checks run one by one: the same events, the same following peak and state, tick for tick.

The fused pass stands in for both checks only when every element of one stacked comparison holds;
these runs go through the ticks where it must not: a joint whose position gain is zero (position
mode, torque on, yet not watched by the following check), a joint falling out of its window, and
the e-stop that follows.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk import Phase, SafetyState
from agentsdk.loop import StateView

FIXTURES = Path(__file__).parent / "fixtures" / "following"


async def _run(fused: bool, push: bool) -> tuple[list[tuple[Any, ...]], list[bytes], int]:
    safety = {"position_limit_tolerance": 0.005}
    async with agentsdk.connect("mujoco", robot=FIXTURES / "healthy.yaml", safety=safety) as robot:
        wd = robot.safety._watchdogs
        if not fused:
            wd._fused = None
        else:
            assert wd._fused is not None  # the default checks: the fused pass is on
        following = robot.safety.following
        assert following is not None
        peaks: list[bytes] = []
        used = 0
        passes = wd._fused.passes if wd._fused is not None else None
        gain = float(robot.setpoint.kp[0])

        def limp(t: float, st: Any, sp: Any) -> None:
            # the shoulder keeps position mode and torque on, but no position gain: it sags, unwatched
            k = robot.clock.ticks
            if push and k >= 50:
                # no gains, pushed by its feed-forward: the wrist leaves its limits, unwatched by the
                # following check; the measured-position check latches
                sp.kp[1] = sp.kd[1] = 0.0
                sp.effort[1] = 1e9
            elif 50 <= k < 150:
                sp.kp[0] = 0.0  # the reference walks away inside the window: unwatched, no error, no peak
                sp.position[0] = 0.8 + 0.002 * (k - 50)
            elif k >= 150:
                # watched again (a weak gain), pushed away by its feed-forward: outside, the check latches
                sp.kp[0] = 0.01 * gain
                sp.effort[0] = -1e9
            peaks.append(following.peak.tobytes())

        handle = robot.add_tick_hook(Phase.COMMAND, limp)
        if passes is not None:
            fused_checks = wd._fused

            def counting(*args: Any) -> bool:
                nonlocal used
                ok = passes(*args)
                used += ok
                return ok

            fused_checks.passes = counting  # type: ignore[method-assign]
        await robot.clock.sleep(0.8)
        handle.remove()
        assert robot.safety.state is SafetyState.ESTOP
        events = [(e.kind, e.time, e.joint, e.detail) for e in robot.safety.events]
        return events, peaks, used


@pytest.mark.parametrize("push", [False, True], ids=["following", "limits"])
async def test_the_fused_checks_leave_what_the_checks_one_by_one_leave(push: bool) -> None:
    ref_events, ref_peaks, _ = await _run(fused=False, push=push)
    events, peaks, used = await _run(fused=True, push=push)
    assert used >= 40  # the fused pass did stand in for the checks (before the shoulder went limp)
    assert any(kind == ("limit" if push else "following_error") for kind, *_ in ref_events)
    assert events == ref_events
    assert len(peaks) == len(ref_peaks)
    for k, (a, b) in enumerate(zip(peaks, ref_peaks, strict=True)):
        assert a == b, (k, np.frombuffer(a), np.frombuffer(b))


async def test_the_fused_pass_never_stands_in_for_a_check_that_would_fire() -> None:
    """Random states and setpoints around the limits and the windows (NaN, zero gains, joints outside):
    whenever the fused pass answers True, each check run on its own returns None and leaves the same
    following peak; the plain ticks do pass."""
    rng = np.random.default_rng(28)
    async with agentsdk.connect("mock", robot="arm3") as robot:
        wd = robot.safety._watchdogs
        fused = wd._fused
        assert fused is not None
        measured, following = wd._checks
        sp = robot._loop._sp
        lo = np.array([j.lower for j in robot.joints])
        hi = np.array([j.upper for j in robot.joints])
        n = len(lo)
        gains = sp.kp.copy()
        passed = 0
        for case in range(3000):
            q = rng.uniform(lo - 0.15, hi + 0.15) if case % 3 else rng.uniform(lo, hi)
            ref = q + rng.normal(0.0, 0.3 if case % 5 == 0 else 0.05, n)
            kp = gains.copy()
            if case % 7 == 0:
                kp[rng.integers(n)] = 0.0
            if case % 11 == 0:
                (q if case % 2 else ref)[rng.integers(n)] = np.nan
            sp.position[...] = ref
            sp.kp[...] = kp
            st = StateView(q, np.zeros(n), np.zeros(n))
            t = 1.0 + case * robot.control_period
            peak, last_t = following.peak.copy(), following._last_t
            ok = fused.passes(t, q, sp.view)
            fused_peak = following.peak.copy()
            following.peak[...] = peak
            following._last_t = last_t
            m, f = measured(t, st), following(t, st)
            if ok:
                passed += 1
                assert m is None and f is None, (case, m, f)
                assert fused_peak.tobytes() == following.peak.tobytes(), case
            # back to the common state: no joint being timed, the watched mask of every joint
            following._since[:] = np.nan
            following._tracking = False
            sp.kp[...] = gains
            following(t, StateView(sp.position, np.zeros(n), np.zeros(n)))
        assert passed >= 500, passed
