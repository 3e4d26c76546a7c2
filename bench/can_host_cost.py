"""The CAN host's cost per control cycle: CPU and system calls of one process driving mit_leg on vcan0.

Not a test. Meant for user-mode Linux (``scripts/run-in-vcan.sh``), where every system call and
every clock read traps into the guest kernel, so the host's per-cycle system calls decide whether
it holds its rate on a slow one-vCPU VM (CI's). For each control rate it

1. starts the MIT motor emulator for a copy of mit_leg's robot.yaml on vcan0 (a separate process
   at a real-time priority, as in the vcan test suite), always from this checkout;
2. runs a host process (``agentsdk.connect("can", ...)``) from the checkout under test that
   holds the leg's joints (position mode, torque on) for ``--seconds`` and reports, over that
   window only, the CPU time it used (``getrusage``: every thread of the process), control
   ticks, periods skipped (missed deadlines) and motor-cycles whose reply missed the deadline;
3. with ``--strace [HZ]`` (default 20 Hz: a traced host in the VM is several times slower),
   runs the host twice more at that rate under ``strace -f -c``, for a third of ``--seconds``
   (at least 1 s) and three times that, and divides the difference of the system-call counts
   by the difference of the ticks: the system calls per control cycle, start-up and shut-down
   cancelled out.

``--baseline PATH`` measures another checkout the same way in the same run (e.g. a
``git worktree`` of an older commit) and prints the ratios against it. Usage::

    scripts/run-in-vcan.sh python bench/can_host_cost.py --rates 50,100 --strace 20
    git worktree add --detach /tmp/base a65e4ac
    scripts/run-in-vcan.sh python bench/can_host_cost.py --baseline /tmp/base --strace --json out.json
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import importlib
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------ the host process
async def host(robot_yaml: str, seconds: float) -> dict[str, Any]:
    """Connect, wave for ``seconds`` and report this process's cost over that window."""
    import agentsdk
    from agentsdk import JointCommand

    can_module = importlib.import_module("agentsdk.backends.can")
    if not hasattr(can_module, "CanBackend"):  # an older checkout (before the *Backend names), installed entry point
        setattr(can_module, "CanBackend", can_module.CanController)  # noqa: B010

    opts: dict[str, Any] = {"max_missed_replies": 1000, "open_timeout": 2.0}
    if os.environ.get("CAN_HOST_COST_TRACED"):
        # strace slows every system call several-fold: a longer stall timeout (the heartbeat's
        # period, min(5 ms, timeout / 10), and so the calls counted per tick, stay the same)
        opts["safety"] = {"stall_timeout": 2.0}
    async with agentsdk.connect("can", robot=robot_yaml, **opts) as robot:
        here = (await robot.read()).positions()
        await robot.command(JointCommand("position", here))  # hold where the motors are, torque on
        await robot.clock.sleep(0.5)  # warm up: first ticks, allocations, caches
        stats = robot.backend.stats  # type: ignore[attr-defined]
        period = robot.control_period
        missed0 = sum(s.missed for s in stats)
        late0 = sum(s.late for s in stats)
        ticks0, skipped0 = robot.ticks, robot.missed_deadlines
        ru0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
        end = t0 + seconds
        while time.monotonic() < end:
            await robot.clock.sleep(min(0.5, max(0.0, end - time.monotonic())))
        ru1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
        ticks = robot.ticks - ticks0
        cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
        return {
            "rate": 1.0 / period,
            "wall_s": t1 - t0,
            "ticks": ticks,
            "expected_ticks": round((t1 - t0) / period),
            "missed_deadlines": robot.missed_deadlines - skipped0,
            "missed_replies": sum(s.missed for s in stats) - missed0,
            "late_replies": sum(s.late for s in stats) - late0,
            "motors": len(stats),
            "cpu_s": cpu,
            "user_s": ru1.ru_utime - ru0.ru_utime,
            "sys_s": ru1.ru_stime - ru0.ru_stime,
            "cpu_frac": cpu / (t1 - t0),
            "cpu_per_tick_us": cpu / max(ticks, 1) * 1e6,
            "ctx_switches": (ru1.ru_nvcsw - ru0.ru_nvcsw) + (ru1.ru_nivcsw - ru0.ru_nivcsw),
            "total_ticks": robot.ticks,
        }


# ------------------------------------------------------------------------------ orchestration
def leg_copy(tree: Path, directory: Path, rate: float) -> str:
    """mit_leg's robot.yaml of ``tree`` at ``rate`` Hz, free-rotor settings (as the vcan suite's copy)."""
    import yaml

    src = tree / "robots" / "mit_leg" / "robot.yaml"
    cfg = yaml.safe_load(src.read_text())
    cfg["description"] = str(src.parent / cfg["description"])
    cfg["update_rate"] = rate
    cfg["backends"]["can"]["timeout"] = max(0.025, 2.5 / rate)
    cfg["gravity_compensation"] = False
    if "inverse_dynamics" in (tree / "agentsdk" / "config.py").read_text():
        cfg["inverse_dynamics"] = False
    dst = directory / "mit_leg" / "robot.yaml"
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(yaml.safe_dump(cfg))
    return str(dst)


def _env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree)
    env.pop("PYTHONSTARTUP", None)
    return env


def run_host(tree: Path, robot_yaml: str, seconds: float, strace_out: str | None = None) -> dict[str, Any]:
    """One host process from ``tree``; its JSON report (and ``strace -f -c`` into ``strace_out``)."""
    argv = [sys.executable, str(Path(__file__).resolve()), "--child", robot_yaml, "--seconds", str(seconds)]
    env = _env(tree)
    if strace_out is not None:
        argv = ["strace", "-f", "-c", "-o", strace_out, *argv]
        env["CAN_HOST_COST_TRACED"] = "1"
    res = subprocess.run(argv, env=env, cwd=tree, capture_output=True, text=True, timeout=600)
    for line in reversed(res.stdout.splitlines()):
        if line.startswith("{"):
            return dict(json.loads(line))
    raise RuntimeError(f"host run failed ({res.returncode}):\n{res.stdout[-2000:]}\n{res.stderr[-4000:]}")


def parse_strace(path: str) -> collections.Counter[str]:
    """Calls per system call from an ``strace -c`` summary."""
    out: collections.Counter[str] = collections.Counter()
    for line in Path(path).read_text().splitlines():
        m = re.match(r"\s*[\d.]+\s+[\d.]+\s+\d+\s+(\d+)\s+(?:\d+\s+)?(\w+)\s*$", line)
        if m and m.group(2) != "total":
            out[m.group(2)] += int(m.group(1))
    return out


def syscalls_per_tick(tree: Path, robot_yaml: str, seconds: float) -> dict[str, Any]:
    """System calls per control cycle: two strace'd runs of different length, their difference per tick."""
    with tempfile.TemporaryDirectory() as tmp:
        a, b = f"{tmp}/short", f"{tmp}/long"
        ra = run_host(tree, robot_yaml, seconds, a)
        rb = run_host(tree, robot_yaml, 3 * seconds, b)
        ca, cb = parse_strace(a), parse_strace(b)
    dt = rb["total_ticks"] - ra["total_ticks"]
    per = {name: (cb[name] - ca[name]) / dt for name in set(ca) | set(cb)}
    per = {k: round(v, 2) for k, v in sorted(per.items(), key=lambda kv: -kv[1]) if abs(v) >= 0.05}
    return {"per_tick": (sum(cb.values()) - sum(ca.values())) / dt, "by_call": per,
            "ticks": dt, "missed_deadlines_traced": rb["missed_deadlines"]}


def measure(tree: Path, rates: list[float], seconds: float, strace: float | None) -> dict[str, Any]:
    """One row per rate (plus ``"strace"``: system calls per tick at ``strace`` Hz, when given)."""
    # (imported here: a --child run has another checkout on its path, whose bench may lack the module)
    from agentsdk.bench.can_emulator import emulator_process

    out: dict[str, Any] = {}
    runs: list[tuple[str, float]] = [(f"{rate:g}", rate) for rate in rates]
    if strace:
        runs.append(("strace", strace))
    for key, rate in runs:
        with tempfile.TemporaryDirectory() as tmp:
            emu_yaml = leg_copy(ROOT, Path(tmp) / "emu", rate)
            host_yaml = leg_copy(tree, Path(tmp) / "host", rate)
            with emulator_process(emu_yaml, realtime=True):
                if key == "strace":
                    out[key] = syscalls_per_tick(tree, host_yaml, max(1.0, seconds / 3))
                    out[key]["rate"] = rate
                else:
                    out[key] = run_host(tree, host_yaml, seconds)
    return out


def table(name: str, res: dict[str, Any]) -> None:
    for rate, r in res.items():
        if rate == "strace":
            top = ", ".join(f"{k} {v:g}" for k, v in list(r["by_call"].items())[:8])
            print(f"{name[-16:]:>16} {r['rate']:>5g} Hz  system calls/tick {r['per_tick']:.1f} "
                  f"(strace'd: {r['missed_deadlines_traced']} periods skipped; {top})")
            continue
        line = (f"{name[-16:]:>16} {rate:>5} Hz  cpu {100 * r['cpu_frac']:5.1f} % of a CPU  "
                f"{r['cpu_per_tick_us']:7.0f} us/tick  ticks {r['ticks']}/{r['expected_ticks']}  "
                f"skipped periods {r['missed_deadlines']}  "
                f"missed replies {r['missed_replies']}/{r['ticks'] * r['motors']}  late {r['late_replies']}")
        print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", metavar="ROBOT_YAML", help=argparse.SUPPRESS)
    ap.add_argument("--rates", default="50,100", help="control rates [Hz], comma-separated")
    ap.add_argument("--seconds", type=float, default=5.0, help="measured window per run [s]")
    ap.add_argument("--strace", type=float, nargs="?", const=20.0, default=None, metavar="HZ",
                    help="also count system calls per tick (strace -f -c) at HZ (default 20: traced, the VM "
                         "is several times slower)")
    ap.add_argument("--baseline", type=Path, action="append", default=[],
                    help="another checkout to measure the same way, ratios printed (repeatable)")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(asyncio.run(host(args.child, args.seconds))), flush=True)
        return
    if not Path("/sys/class/net/vcan0").exists():
        sys.exit("no vcan0: run inside scripts/run-in-vcan.sh")
    if args.strace and not shutil.which("strace"):
        sys.exit("--strace needs strace (apt-get install strace)")
    rates = [float(r) for r in args.rates.split(",")]
    results = {"this": measure(ROOT, rates, args.seconds, args.strace)}
    for base in args.baseline:
        results[str(base)] = measure(base.resolve(), rates, args.seconds, args.strace)
    for name, res in results.items():
        table(name, res)
    for base in args.baseline:
        for rate, r in results["this"].items():
            b = results[str(base)][rate]
            if rate == "strace":
                print(f"this/{base}: system calls per tick {r['per_tick'] / b['per_tick']:.2f}x")
            else:
                print(f"this/{base} {rate} Hz: cpu per tick {r['cpu_per_tick_us'] / b['cpu_per_tick_us']:.2f}x")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    print(json.dumps(results))


if __name__ == "__main__":
    main()
