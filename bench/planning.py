"""Trajectory planning time: ``agentsdk.trajectory.plan`` vs the raw ruckig calls it wraps.

Problem: a 7-joint arm with Franka-like position and velocity limits (3.75-10 rad/s²,
100-200 rad/s³), 10 fixed-seed random waypoints (the same family as
tests/test_trajectory.py), from rest at the first waypoint to rest at the last.

Baselines, timed in the same run with the same ruckig build:

* ``ruckig p2p per segment``: one rest-to-rest ruckig ``calculate`` per segment
  (9 calls, one reused ``Ruckig``/``InputParameter``/``Trajectory``), the least a
  jerk-limited plan through the waypoints has to compute;
* ``replay of plan()'s ruckig calls``: every ``calculate`` that ``plan()`` itself
  makes (recorded once, then replayed raw), i.e. the ruckig share of ``plan()``;
  the rest is the SDK's Python (through-velocity search, limit checks, breakpoints,
  building the Trajectory).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from agentsdk.bench.common import Comparison, Section, Table, fmt, median, progress, spread

LOWER = np.array([-2.8, -1.7, -2.8, -3.0, -2.8, 0.0, -2.8])
UPPER = np.array([2.8, 1.7, 2.8, -0.07, 2.8, 3.7, 2.8])
VMAX = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
AMAX = np.array([7.5, 3.75, 5.0, 6.25, 7.5, 10.0, 10.0])
JMAX = np.array([100.0, 100.0, 100.0, 100.0, 200.0, 200.0, 200.0])
SEED = 0
N_WAYPOINTS = 10


def arm_joints() -> list[Any]:
    from agentsdk.types import JointInfo

    return [
        JointInfo(
            name=f"a{i}",
            type="revolute",
            lower=float(LOWER[i]),
            upper=float(UPPER[i]),
            max_velocity=float(VMAX[i]),
            max_effort=10.0,
            max_acceleration=float(AMAX[i]),
            max_jerk=float(JMAX[i]),
        )
        for i in range(7)
    ]


def arm_waypoints(seed: int = SEED, n: int = N_WAYPOINTS) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return LOWER + (UPPER - LOWER) * (0.1 + 0.8 * rng.random((n, 7)))


def _new_otg() -> tuple[Any, Any, Any]:
    from ruckig import InputParameter, Ruckig, Trajectory

    inp = InputParameter(7)
    inp.max_velocity = VMAX.tolist()
    inp.max_acceleration = AMAX.tolist()
    inp.max_jerk = JMAX.tolist()
    return Ruckig(7), inp, Trajectory(7)


def _p2p_segments(wps: np.ndarray) -> float:
    """One rest-to-rest ruckig solve per segment; returns the summed duration (s)."""
    from ruckig import Result

    otg, inp, traj = _new_otg()
    zero = [0.0] * 7
    total = 0.0
    rows = wps.tolist()
    for i in range(len(rows) - 1):
        inp.current_position = rows[i]
        inp.current_velocity = zero
        inp.current_acceleration = zero
        inp.target_position = rows[i + 1]
        inp.target_velocity = zero
        inp.target_acceleration = zero
        if otg.calculate(inp, traj) != Result.Working:
            raise RuntimeError("ruckig failed")
        total += traj.duration
    return total


def _record_plan_calls(wps: np.ndarray, joints: list[Any]) -> list[tuple[list[float], ...]] | None:
    """The inputs of every ruckig solve ``plan()`` makes."""
    from agentsdk import trajectory as tr

    with tr.recording_solves() as calls:
        tr.plan(wps, joints)
    return calls


def _replay(calls: list[tuple[list[float], ...]]) -> int:
    """Replay recorded ruckig problems raw; returns how many solved."""
    from ruckig import Result

    otg, inp, traj = _new_otg()
    zero = [0.0] * 7
    ok = 0
    for q0, v0, a0, q1, v1 in calls:
        inp.current_position = q0
        inp.current_velocity = v0
        inp.current_acceleration = a0
        inp.target_position = q1
        inp.target_velocity = v1
        inp.target_acceleration = zero
        if otg.calculate(inp, traj) == Result.Working:
            ok += 1
    return ok


def _time(fn: Any, runs: int, warmup: int = 3) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def _profile_plan(wps: np.ndarray, joints: list[Any], runs: int = 10, top: int = 8) -> Table:
    """cProfile of plan(): the top self-time functions (for optimizing it)."""
    import cProfile
    import os
    import pstats

    from agentsdk.trajectory import plan

    prof = cProfile.Profile()
    prof.enable()
    for _ in range(runs):
        plan(wps, joints)
    prof.disable()
    st = pstats.Stats(prof)
    total = st.total_tt  # type: ignore[attr-defined]
    rows = []
    entries = sorted(st.stats.items(), key=lambda kv: -kv[1][2])  # type: ignore[attr-defined]
    for (path, line, func), (_cc, nc, tt, ct, _callers) in entries[:top]:
        where = func.strip("<>") if path == "~" else f"{func}  ({os.path.basename(path)}:{line})"
        rows.append([where, fmt(tt / runs * 1e3), fmt(ct / runs * 1e3), fmt(nc / runs), f"{100 * tt / total:.1f}%"])
    return Table(
        f"cProfile of plan(): top {top} self-time functions (profiled {fmt(total / runs * 1e3)} ms per plan)",
        ("function", "self ms/plan", "cum ms/plan", "calls/plan", "% of total"),
        rows,
    )


def run(quick: bool = False) -> Section:
    from agentsdk.trajectory import plan

    runs = 20 if quick else 100
    joints = arm_joints()
    wps = arm_waypoints()
    sec = Section(
        "planning",
        f"trajectory planning, 7 joints x {N_WAYPOINTS} waypoints (seed {SEED}), median of {runs} runs",
    )
    progress(f"planning: plan() and raw ruckig baselines, {runs} runs each")
    traj = plan(wps, joints)
    calls = _record_plan_calls(wps, joints)
    p2p_duration = _p2p_segments(wps)

    # interleave the three measurements in blocks so that load changes hit them alike
    plan_ms: list[float] = []
    p2p_ms: list[float] = []
    replay_ms: list[float] = []
    blocks = 5
    per = max(runs // blocks, 1)
    for _ in range(blocks):
        plan_ms += _time(lambda: plan(wps, joints), per)
        p2p_ms += _time(lambda: _p2p_segments(wps), per)
        if calls:
            replay_ms += _time(lambda: _replay(calls), per)

    plan_m = median(plan_ms)
    sec.comparisons.append(
        Comparison(
            "plan() vs one ruckig rest-to-rest solve per segment (9)",
            "ms",
            median(p2p_ms),
            plan_m,
            baseline_label="raw ruckig p2p",
            extra={"plan_ms": spread(plan_ms), "baseline_ms": spread(p2p_ms)},
        )
    )
    if calls:
        sec.comparisons.append(
            Comparison(
                f"plan() vs replay of its own {len(calls)} ruckig solves",
                "ms",
                median(replay_ms),
                plan_m,
                baseline_label="raw ruckig replay",
                extra={"baseline_ms": spread(replay_ms)},
            )
        )
    else:
        sec.notes.append("agentsdk.trajectory._ruckig.RuckigSolver not found: the replay baseline was skipped")
    sec.tables.append(
        Table(
            "planned motion",
            ("what", "value"),
            [
                ["plan() trajectory duration (through-velocities optimized)", f"{traj.duration:.3f} s"],
                ["sum of rest-to-rest segment durations (p2p baseline)", f"{p2p_duration:.3f} s"],
                ["trajectory points (profile breakpoints)", str(len(traj.points))],
                ["ruckig solves made by plan()", str(len(calls)) if calls else "-"],
                ["plan() time per ruckig solve", f"{fmt(plan_m / len(calls) * 1e3)} µs" if calls else "-"],
                [
                    "raw ruckig time per solve (replay)",
                    f"{fmt(median(replay_ms) / len(calls) * 1e3)} µs" if calls else "-",
                ],
                ["plan() min / max", f"{fmt(min(plan_ms))} / {fmt(max(plan_ms))} ms"],
            ],
        )
    )
    sec.tables.append(_profile_plan(wps, joints))
    if calls:
        share = median(replay_ms) / plan_m
        sec.notes.append(
            f"ruckig itself is {100 * share:.0f} % of plan(); the other {100 * (1 - share):.0f} % is the SDK's Python "
            "around it (through-velocity search, position-extrema checks, breakpoints, Trajectory construction)."
        )
    sec.data = {
        "runs": runs,
        "plan_ms": plan_ms,
        "p2p_ms": p2p_ms,
        "replay_ms": replay_ms,
        "ruckig_solves_in_plan": len(calls) if calls else None,
        "trajectory_duration_s": traj.duration,
        "p2p_duration_sum_s": p2p_duration,
        "trajectory_points": len(traj.points),
    }
    return sec


if __name__ == "__main__":
    print(run().render())
