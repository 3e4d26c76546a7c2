"""Safety latency benchmark: e-stop and loop-stall detection (wall time).

Not a test: prints distributions (p50 / p99 / max over N trials) as a table and as JSON.

(a) e-stop latency, per backend, with a trajectory running (the control loop busy in lockstep):

    threadsafe   ``robot.estop_threadsafe(0)`` called from another thread -> it returns, measured in
                 that thread (category 0 removes torque in the calling thread: the backend's
                 ``emergency_stop`` has returned when it does)
    api-return   ``await robot.estop(0)`` called -> the await returns (torque off)

Both are observed through the public API only (``robot.torque_enabled`` is checked after each stop).

(b) stall-detection latency from the watchdog thread's own view, ``stall_latency -
    stall_timeout`` (``stall_latency`` = last heartbeat -> the watchdog fired; it stops the
    backend right after), for a few
    ``stall_timeout`` values and two kinds of stall: ``sleep`` (the loop thread blocks in
    ``time.sleep``, GIL released) and ``busy`` (a pure-Python spin holding the GIL, so the
    watchdog thread waits for the interpreter's switch interval, ``sys.getswitchinterval()``).

Usage::

    python bench/safety_latency.py                      # mock + mujoco (+ pybullet if available)
    python bench/safety_latency.py --trials 50 --stall-trials 20 --json out.json
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import random
import sys
import threading
import time
from typing import Any

import numpy as np

import agentsdk
from agentsdk import Trajectory, TrajectoryPoint

MS = 1e3


def stats(samples: list[float]) -> dict[str, float]:
    a = np.asarray(samples, dtype=float)
    return {
        "n": len(a),
        "p50_ms": float(np.percentile(a, 50) * MS),
        "p99_ms": float(np.percentile(a, 99) * MS),
        "max_ms": float(a.max() * MS),
        "mean_ms": float(a.mean() * MS),
    }


async def rearm(robot: agentsdk.Robot) -> None:
    if robot.safety.state is not agentsdk.SafetyState.OK:
        await robot.reset()
        await robot.enable()


def moving(robot: agentsdk.Robot, k: int) -> agentsdk.Motion:
    """A trajectory that keeps joint1 and joint3 moving for a while."""
    sign = 1.0 if k % 2 == 0 else -1.0
    return robot.follow(Trajectory(["joint1", "joint3"], [TrajectoryPoint(3.0, [sign * 1.5, -sign * 1.5])]))


# ------------------------------------------------------------------ e-stop
async def bench_estop(backend: str, trials: int, seed: int) -> dict[str, dict[str, float]]:
    rng = random.Random(seed)
    threadsafe: list[float] = []
    api_return: list[float] = []
    async with agentsdk.connect(backend, robot="arm3") as robot:
        for k in range(trials):
            # estop_threadsafe(0) from a "button" thread, at a random moment while the loop is busy
            await rearm(robot)
            motion = moving(robot, k)
            called: list[float] = []
            delay = rng.uniform(0.001, 0.005)

            def press(delay: float = delay, called: list[float] = called) -> None:
                time.sleep(delay)
                t0 = time.perf_counter()
                robot.estop_threadsafe(0)
                called.append(time.perf_counter() - t0)

            button = threading.Thread(target=press, name="bench-estop-button")
            button.start()
            while robot.torque_enabled:
                await robot.clock.sleep(robot.control_period)
            await asyncio.to_thread(button.join)
            assert not robot.torque_enabled
            threadsafe.append(called[0])
            await motion

            # await robot.estop(0) from a behavior, trajectory running
            await rearm(robot)
            motion = moving(robot, k)
            await robot.clock.sleep(rng.uniform(0.01, 0.2))
            t0 = time.perf_counter()
            await robot.estop(0)
            t1 = time.perf_counter()
            assert not robot.torque_enabled
            api_return.append(t1 - t0)
            await motion
    return {"threadsafe": stats(threadsafe), "api-return": stats(api_return)}


# ------------------------------------------------------------------- stall
def _block(robot: agentsdk.Robot, kind: str, prev: float | None, limit: float) -> None:
    """Block the event loop (this thread) until the watchdog has fired, or ``limit`` s passed."""
    deadline = time.monotonic() + limit
    safety = robot.safety
    if kind == "sleep":
        while safety.stall_detected_at == prev and time.monotonic() < deadline:
            time.sleep(0.0002)
    else:
        while safety.stall_detected_at == prev and time.monotonic() < deadline:
            pass


async def bench_stall(backend: str, stall_timeout: float, kind: str, trials: int) -> dict[str, float]:
    over: list[float] = []
    # realtime: in lockstep the stall watchdog is off (a simulated robot does not move while the loop stalls)
    async with agentsdk.connect(backend, robot="arm3", realtime=True, safety={"stall_timeout": stall_timeout}) as robot:
        for _ in range(trials):
            await rearm(robot)
            await asyncio.sleep(0.01)  # let the heartbeat run normally first
            prev = robot.safety.stall_detected_at
            _block(robot, kind, prev, stall_timeout + 1.0)
            if robot.safety.stall_detected_at == prev:
                raise RuntimeError(f"stall of {stall_timeout + 1.0:g} s not detected (stall_timeout={stall_timeout:g})")
            assert robot.safety.stall_latency is not None
            over.append(robot.safety.stall_latency - stall_timeout)
            await robot.clock.sleep(robot.control_period)  # drain the watchdog's event
    return stats(over)


# -------------------------------------------------------------------- main
def available(name: str) -> bool:
    try:
        agentsdk.load_backend(name)
    except Exception as exc:
        print(f"# skipping backend {name!r}: {exc}", file=sys.stderr)
        return False
    return True


def table(rows: list[tuple[str, str, dict[str, float]]], header: tuple[str, str]) -> str:
    lines = [f"{header[0]:<12} {header[1]:<22} {'n':>4} {'p50 ms':>9} {'p99 ms':>9} {'max ms':>9}"]
    for a, b, s in rows:
        lines.append(f"{a:<12} {b:<22} {s['n']:>4} {s['p50_ms']:>9.3f} {s['p99_ms']:>9.3f} {s['max_ms']:>9.3f}")
    return "\n".join(lines)


async def _run(args: argparse.Namespace) -> dict[str, Any]:
    t_start = time.perf_counter()
    backends = [b for b in args.backends if available(b)]
    result: dict[str, Any] = {
        "python": sys.version.split()[0],
        "switch_interval_ms": sys.getswitchinterval() * MS,
        "trials": args.trials,
        "stall_trials": args.stall_trials,
        "estop": {},
        "stall": {},
    }
    rows: list[tuple[str, str, dict[str, float]]] = []
    for b in backends:
        res = await bench_estop(b, args.trials, args.seed)
        result["estop"][b] = res
        rows += [(b, what, s) for what, s in res.items()]
    print("(a) e-stop latency: call -> backend stopped (wall time)")
    print(table(rows, ("backend", "measure")))
    print()

    rows = []
    stall_backend = args.stall_backend
    if available(stall_backend):
        for kind in args.stall_kinds:
            for timeout in args.stall_timeouts:
                s = await bench_stall(stall_backend, timeout, kind, args.stall_trials)
                result["stall"].setdefault(kind, {})[f"{timeout:g}"] = s
                rows.append((kind, f"stall_timeout={timeout:g} s", s))
        print(f"(b) stall detection on {stall_backend}: stall_latency - stall_timeout (watchdog thread's view)")
        print(table(rows, ("stall kind", "setting")))
        print()
    result["wall_s"] = time.perf_counter() - t_start
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backends", nargs="+", default=["mock", "mujoco", "pybullet"])
    p.add_argument("--trials", type=int, default=50, help="e-stop trials per backend and measure")
    p.add_argument("--stall-backend", default="mock")
    p.add_argument("--stall-timeouts", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.25])
    p.add_argument("--stall-kinds", nargs="+", choices=["sleep", "busy"], default=["sleep", "busy"])
    p.add_argument("--stall-trials", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="PATH", help="also write the JSON here")
    args = p.parse_args(argv)
    # the stall watchdog logs every detected stall with the loop's stack: keep the output readable
    logging.basicConfig(level=logging.CRITICAL)
    result = asyncio.run(_run(args))
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
