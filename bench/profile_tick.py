"""Profile of the lockstep control tick: where a tick's time goes, top entries by self time.

Not a benchmark figure (cProfile inflates every Python call): a ranking, used for the
before/after tables in ``bench/NOTES.md``. Runs ``agentsdk.connect(backend, robot)`` in
lockstep holding its pose (``hold``) or following a planned trajectory (``track``) for
``--seconds`` of simulated time, profiled with the loop thread's CPU time.

``--phases`` measures instead, without cProfile, where a tick's wall time goes: clock stamps
(``time.perf_counter``) taken by hooks at the ends of the tick's phases, so the figures are
real microseconds (each stamp costs ~0.1 µs), beside the raw loop on the backend's model
(MuJoCo: ``mj_step`` with the same frame skip)::

    commands+limits   COMMAND hooks (motions) and LIMIT hooks (the safety filter), the loop's own code
    backend           write (servo law, model terms), step (the simulator and its checks), clock, read, gate
    observe           OBSERVE hooks (safety checks, command watchdog, feedback, recorders)

Usage::

    python -m agentsdk.bench.profile_tick                       # arm3 on mujoco and pybullet, hold and track
    python -m agentsdk.bench.profile_tick --backend mujoco --robot humanoid --what track --top 15
    python -m agentsdk.bench.profile_tick --phases --backend mujoco   # real µs per phase, no profiler
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import pstats
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import agentsdk
from agentsdk.bench.overhead import load_robot, waypoints


def _label(func: tuple[str, int, str]) -> str:
    filename, line, name = func
    if filename == "~":  # a built-in: pstats names it "<built-in method x>" / "<method 'x' of 'y' objects>"
        return name.strip("<>")
    path = Path(filename)
    parts = path.parts
    for root in ("agentsdk", "backends", "bench"):
        if root in parts:
            i = len(parts) - 1 - parts[::-1].index(root)
            return f"{name}  ({'/'.join(parts[i:])}:{line})"
    return f"{name}  ({path.name}:{line})"


async def _run(backend: str, robot: str, what: str, seconds: float, prof: cProfile.Profile) -> int:
    rb = load_robot(robot)
    _wps, traj = waypoints(rb, seconds)
    async with agentsdk.connect(backend, robot) as r:
        await r.clock.sleep(0.05)  # warm-up (first-tick views, caches)
        t0 = r.ticks
        prof.enable()
        if what == "track":
            await r.follow(traj)
        else:
            await r.clock.sleep(seconds)
        prof.disable()
        return r.ticks - t0


def profile(backend: str, robot: str, what: str, seconds: float = 4.0, top: int = 12) -> str:
    """Profile one lockstep run and return the report (a header line and the top-``top`` table)."""
    prof = cProfile.Profile(time.thread_time)
    ticks = asyncio.run(_run(backend, robot, what, seconds, prof))
    st = pstats.Stats(prof)
    stats = st.stats  # type: ignore[attr-defined]
    total = sum(v[2] for v in stats.values())
    calls = sum(v[1] for v in stats.values())
    sdk = sum(v[2] for k, v in stats.items() if any(f"/{d}/" in k[0] for d in ("agentsdk", "backends")))
    rows = sorted(stats.items(), key=lambda kv: kv[1][2], reverse=True)[:top]
    table = [(_label(k), v[2] / ticks * 1e6, v[3] / ticks * 1e6, v[1] / ticks, 100 * v[2] / total) for k, v in rows]
    width = max(len("function"), *(len(r[0]) for r in table))
    out = [
        f"cProfile, {robot} on {backend}, lockstep {what}: {ticks} ticks, {total / ticks * 1e6:.0f} µs/tick profiled "
        f"(of which {sdk / ticks * 1e6:.1f} in agentsdk code), {calls / ticks:.0f} Python/C calls per tick; "
        f"top {top} by self time",
        f"{'function':<{width}}  self µs/tick  cum µs/tick  calls/tick  % of total",
        f"{'-' * width}  {'-' * 12}  {'-' * 11}  {'-' * 10}  {'-' * 10}",
    ]
    for name, self_us, cum_us, per_tick, pct in table:
        out.append(f"{name:<{width}}  {self_us:12.3g}  {cum_us:11.3g}  {per_tick:10.3g}  {pct:9.1f}%")
    return "\n".join(out)


class _Stamps:
    """perf_counter stamps at the ends of a tick's phases (hooks of extreme order), summed per segment."""

    SEGMENTS = ("commands+limits", "backend", "observe")

    def __init__(self, robot: agentsdk.Robot) -> None:
        from agentsdk.loop import Phase

        self.sums = dict.fromkeys(self.SEGMENTS, 0.0)
        self.n = 0
        self.on = False
        self._last = 0.0
        big = 1 << 30
        robot.add_tick_hook(Phase.LIMIT, self._stamp("commands+limits"), order=big)
        robot.add_tick_hook(Phase.OBSERVE, self._stamp("backend"), order=-big)
        robot.add_tick_hook(Phase.OBSERVE, self._stamp("observe", last=True), order=big)

    def _stamp(self, name: str, last: bool = False) -> Any:
        sums = self.sums
        clock = time.perf_counter

        def hook(t: float, st: Any, sp: Any) -> None:
            now = clock()
            if self.on and self._last:
                sums[name] += now - self._last
                if last:
                    self.n += 1
            self._last = clock()  # (the stamp's own cost is left out of the next segment)

        return hook


async def _run_phases(backend: str, robot: str, what: str, seconds: float) -> tuple[_Stamps, float]:
    rb = load_robot(robot)
    _wps, traj = waypoints(rb, seconds)
    async with agentsdk.connect(backend, robot) as r:
        stamps = _Stamps(r)
        await r.clock.sleep(0.05)
        if what == "track":
            motion = r.follow(traj)
        stamps.on = True
        t0 = r.ticks
        w0 = time.perf_counter()
        await r.clock.sleep(seconds)
        wall = time.perf_counter() - w0
        stamps.on = False
        if what == "track":
            motion.cancel()
            await motion
        return stamps, wall / (r.ticks - t0)


def _raw_step_us(robot: str, ticks: int) -> float:
    """µs per tick of ``mj_step(nstep)`` alone on the backend's model (MuJoCo only)."""
    import mujoco

    from agentsdk.bench.overhead import RawMujoco

    raw = RawMujoco(load_robot(robot))
    raw.data.ctrl[:] = raw.kp * raw.positions()
    m, d, n = raw.model, raw.data, raw.nsub
    step = mujoco.mj_step
    t0 = time.perf_counter()
    for _ in range(ticks):
        step(m, d, nstep=n)
    return (time.perf_counter() - t0) / ticks * 1e6


def phases(backend: str, robot: str, what: str, seconds: float = 2.0, repeats: int = 5) -> str:
    """Real µs per tick and phase (median of ``repeats`` runs), beside the raw step on MuJoCo."""
    rows: dict[str, list[float]] = {k: [] for k in (*_Stamps.SEGMENTS, "tick (wall)", "raw mj_step")}
    for _ in range(repeats):
        stamps, per_tick = asyncio.run(_run_phases(backend, robot, what, seconds))
        for k in _Stamps.SEGMENTS:
            rows[k].append(stamps.sums[k] / max(stamps.n, 1) * 1e6)
        rows["tick (wall)"].append(per_tick * 1e6)
        if backend == "mujoco":
            rows["raw mj_step"].append(_raw_step_us(robot, stamps.n))
    out = [f"{robot} on {backend}, lockstep {what}: µs per tick, median of {repeats} x {seconds:g} s (real time)"]
    for k, v in rows.items():
        if v:
            out.append(f"  {k:<16} {statistics.median(v):8.2f}")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """Command line: print the profiles."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", action="append", help="mujoco, pybullet (default: both)")
    ap.add_argument("--robot", default="arm3")
    ap.add_argument("--what", action="append", choices=("hold", "track"), help="default: both")
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated seconds profiled")
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--phases", action="store_true", help="real µs per tick phase (no profiler)")
    args = ap.parse_args(argv)
    if args.phases:
        for backend in args.backend or ["mujoco", "pybullet"]:
            for what in args.what or ["hold", "track"]:
                sys.stdout.write(phases(backend, args.robot, what, min(args.seconds, 2.0)) + "\n\n")
        return 0
    for backend in args.backend or ["mujoco", "pybullet"]:
        for what in args.what or ["hold", "track"]:
            sys.stdout.write(profile(backend, args.robot, what, args.seconds, args.top) + "\n\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
