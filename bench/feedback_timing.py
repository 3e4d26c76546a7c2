"""Benchmark: timing of the fixed-rate feedback agent in real time, next to a bare asyncio baseline.

    /work/venv/bin/python bench/feedback_timing.py                    # 500 Hz and 1 kHz, 3 s each
    /work/venv/bin/python bench/feedback_timing.py --duration 5 --rates 250 500 1000 --json out.json

Not a test: wall-clock numbers depend on the machine and its load. For each rate,
in one process and with the robot connected (its control loop running on the
same event loop, as in a real behavior), it measures, one after the other:

* ``asyncio.sleep(period)``: the naive loop (sleeps a period after the work: drifts);
* ``asyncio.sleep(deadline)``: bare asyncio on absolute deadlines (no drift, timer precision only);
* ``run_feedback``: the feedback agent (read, update, command through the safety
  layer; RealtimeClock.sleep_until: sleep, then spin the last ~1.5 ms).

All three are reduced with :meth:`LoopStats.from_wake_times` / the agent's own
recorder, the same definitions: period error = |actual period - scheduled period|
between consecutive wake-ups; missed = deadlines skipped (the baselines never skip).
Prints a table and the JSON of every :class:`LoopStats`. ``agentsdk bench`` calls
:func:`run` (a ``agentsdk.bench.common.Section``: agent vs the absolute-deadline baseline).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import sys
from typing import Any

import agentsdk
from agentsdk import JointCommand, JointState
from agentsdk.feedback import FeedbackAgent, LoopStats, run_feedback


class HoldAgent(FeedbackAgent):
    """Minimal work per period: read the state, command joint1 to stay where it started."""

    async def setup(self, robot: agentsdk.Robot) -> None:
        self.target = {"joint1": float((await robot.read()).position[0])}

    async def update(self, state: JointState) -> JointCommand:
        return JointCommand("position", self.target)


async def naive_sleep_loop(robot: agentsdk.Robot, rate: float, duration: float) -> LoopStats:
    clock, period = robot.clock, 1.0 / rate
    n = round(duration * rate)
    wakes = []
    for _ in range(n):
        wakes.append(clock.now())
        await robot.read()  # the same minimal work as the agent
        await asyncio.sleep(period)
    return LoopStats.from_wake_times(wakes, period)


async def absolute_sleep_loop(robot: agentsdk.Robot, rate: float, duration: float) -> LoopStats:
    clock, period = robot.clock, 1.0 / rate
    n = round(duration * rate)
    start = clock.now()
    wakes, deadlines = [], []
    for k in range(n):
        deadline = start + k * period
        remaining = deadline - clock.now()
        if remaining > 0:
            await asyncio.sleep(remaining)
        wakes.append(clock.now())
        deadlines.append(deadline)
        await robot.read()
    return LoopStats.from_wake_times(wakes, period, deadlines=deadlines)


async def measure(backend: str, robot_name: str, rates: list[float], duration: float) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    async with agentsdk.connect(backend, robot=robot_name, realtime=True) as robot:
        print(
            f"{backend}/{robot_name} realtime, control loop {1 / robot.control_period:g} Hz, "
            f"{duration:g} s per measurement",
            file=sys.stderr,
        )
        for rate in rates:
            loops = (
                ("asyncio.sleep(period)", naive_sleep_loop(robot, rate, duration)),
                ("asyncio.sleep(deadline)", absolute_sleep_loop(robot, rate, duration)),
                ("run_feedback", run_feedback(robot, HoldAgent(), rate, duration=duration)),
            )
            for name, coro in loops:
                stats = await coro
                rows.append({"rate": rate, "loop": name, **stats.as_dict()})
                missed_before = robot.missed_deadlines
                print(
                    f"  {rate:6g} Hz  {name:<24s} done ({stats.count} periods; control loop missed "
                    f"{missed_before} so far)",
                    file=sys.stderr,
                )
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    us = 1e6
    head = (
        f"{'rate':>6s}  {'loop':<24s} {'count':>6s} {'p50 err':>9s} {'p99 err':>9s} {'max err':>9s} "
        f"{'p99 lat':>9s} {'missed':>6s} {'overrun':>7s} {'achieved':>9s}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['rate']:6g}  {r['loop']:<24s} {r['count']:6d} {r['period_error_p50'] * us:8.1f}u "
            f"{r['period_error_p99'] * us:8.1f}u {r['period_error_max'] * us:8.1f}u {r['latency_p99'] * us:8.1f}u "
            f"{r['missed_deadlines']:6d} {r['overruns']:7d} {r['achieved_rate']:8.1f}Hz"
        )
    lines.append("(err = |actual - scheduled period|, lat = wake time - deadline; u = microseconds)")
    return "\n".join(lines)


def run(quick: bool = False) -> Any:
    """Entry point of ``agentsdk bench``: a :class:`agentsdk.bench.common.Section` comparing the agent with the
    absolute-deadline asyncio baseline (the naive loop is in the table and the JSON)."""
    duration = 1.0 if quick else 3.0
    rows = asyncio.run(measure("mock", "arm3", [500.0, 1000.0], duration))
    print(table(rows))
    try:
        from agentsdk.bench.common import Comparison, Section, Table
    except ImportError:  # run outside the bench package
        return {"results": rows}
    us = 1e6
    sec = Section("feedback_timing", "realtime feedback loop timing at 500 Hz and 1 kHz vs a raw asyncio loop")
    for rate in (500.0, 1000.0):
        base = next(r for r in rows if r["rate"] == rate and r["loop"] == "asyncio.sleep(deadline)")
        agent = next(r for r in rows if r["rate"] == rate and r["loop"] == "run_feedback")
        for key, label in (("period_error_p50", "p50"), ("period_error_p99", "p99"), ("period_error_max", "max")):
            sec.comparisons.append(
                Comparison(
                    f"{rate:g} Hz period error {label}",
                    "us",
                    baseline=base[key] * us,
                    sdk=agent[key] * us,
                    baseline_label="asyncio.sleep(deadline)",
                    sdk_label="run_feedback",
                )
            )
        sec.comparisons.append(
            Comparison(
                f"{rate:g} Hz missed deadlines",
                "count",
                baseline=float(base["missed_deadlines"]),
                sdk=float(agent["missed_deadlines"]),
                baseline_label="never skips",
                sdk_label="run_feedback",
                note="the baseline never skips: it bursts to catch up instead",
            )
        )
    sec.tables.append(
        Table(
            "all loops",
            ["rate", "loop", "count", "p50 err us", "p99 err us", "max err us", "p99 lat us", "missed", "overruns"],
            [
                [
                    r["rate"],
                    r["loop"],
                    r["count"],
                    r["period_error_p50"] * us,
                    r["period_error_p99"] * us,
                    r["period_error_max"] * us,
                    r["latency_p99"] * us,
                    r["missed_deadlines"],
                    r["overruns"],
                ]
                for r in rows
            ],
        )
    )
    sec.notes.append(f"mock/arm3 realtime, {duration:g} s per loop; wall-clock figures depend on the machine's load")
    sec.data["results"] = rows
    return sec


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--backend", default="mock")
    p.add_argument("--robot", default="arm3")
    p.add_argument("--rates", type=float, nargs="+", default=[500.0, 1000.0])
    p.add_argument("--duration", type=float, default=3.0, help="seconds per measurement")
    p.add_argument("--quick", action="store_true", help="1 s per measurement")
    p.add_argument("--json", dest="json_path", default=None, help="also write the JSON here")
    args = p.parse_args(argv)
    if args.quick:
        args.duration = 1.0
    rows = asyncio.run(measure(args.backend, args.robot, args.rates, args.duration))
    print(table(rows))
    doc = {
        "benchmark": "feedback_timing",
        "backend": args.backend,
        "robot": args.robot,
        "duration": args.duration,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "results": rows,
    }
    text = json.dumps(doc, indent=2)
    print(text)
    if args.json_path:
        with open(args.json_path, "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
