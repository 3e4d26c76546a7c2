"""Profile of the lockstep control tick: where a tick's time goes, top entries by self time.

Not a benchmark figure (cProfile inflates every Python call): a ranking, used for the
before/after tables in ``bench/NOTES.md``. Runs ``agentsdk.connect(backend, robot)`` in
lockstep holding its pose (``hold``) or following a planned trajectory (``track``) for
``--seconds`` of simulated time, profiled with the loop thread's CPU time.

Usage::

    python -m agentsdk.bench.profile_tick                       # arm3 on mujoco and pybullet, hold and track
    python -m agentsdk.bench.profile_tick --backend mujoco --robot humanoid --what track --top 15
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import pstats
import sys
import time
from pathlib import Path

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


def main(argv: list[str] | None = None) -> int:
    """Command line: print the profiles."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", action="append", help="mujoco, pybullet (default: both)")
    ap.add_argument("--robot", default="arm3")
    ap.add_argument("--what", action="append", choices=("hold", "track"), help="default: both")
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated seconds profiled")
    ap.add_argument("--top", type=int, default=12)
    args = ap.parse_args(argv)
    for backend in args.backend or ["mujoco", "pybullet"]:
        for what in args.what or ["hold", "track"]:
            sys.stdout.write(profile(backend, args.robot, what, args.seconds, args.top) + "\n\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
