"""One awaited command per tick, counted in instructions (issue 28 acceptance 2): the SDK's cycle ÷ the raw loop's.

The cycle is ``bench/overhead.py``'s ``_sdk_wave`` (``await robot.read()``, ``await robot.command(...)``,
``await clock.sleep(period)`` on MuJoCo in lockstep); the baseline is the same file's raw loop
(``RawMujoco.run_wave``: write the setpoint, ``mj_step``, read), the same model, setpoints and rate.

Each is run twice under valgrind's cachegrind (``--cache-sim=no``: instructions only), for ``short``
and ``long`` cycles; instructions per cycle are ``(I_long - I_short) / (long - short)``, so start-up,
imports and the warm-up cancel out. Instruction counts do not move with the machine's load, which
CPU time on a shared 2-core VM does by a factor of two (``bench/NOTES.md``). They are not time: the
SDK's instructions (the interpreter, numpy's ufunc dispatch) run at about two thirds of the raw loop's
rate (mostly ``mj_step``'s C), so the time ratio (``--only overhead``) is higher than this one
(``bench/NOTES.md``, *fifth pass*: 2.95× in instructions, 4.6× in CPU time).

Under valgrind, code runs ~50× slower. The lockstep batch and the inline tick's lease end after
``batch_seconds`` of *wall* time (1 ms by default, ~30 ticks natively): the child sets it to 50 ms,
about as many ticks per lease as natively. ``PYTHONHASHSEED=0`` and ``OPENBLAS_NUM_THREADS=1`` make
the counts repeatable (±0.1 %).

Needs ``valgrind`` (``agentsdk bench --only instructions`` installs it with apt-get when it runs as
root and it is missing). Run: ``python -m agentsdk.bench --only instructions`` or
``python bench/instructions.py [--robot arm3] [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor

from agentsdk.bench.common import Comparison, Section, progress

#: batch_seconds in the child under valgrind (about the native number of ticks per lease, see above)
BATCH_UNDER_VALGRIND = 0.05
#: issue 28 acceptance 2: the SDK's awaited cycle at most this many times the raw loop's
TARGET = 3.0
ROBOTS = ("arm3", "humanoid")


def _child(what: str, n: int, robot: str) -> None:
    """Run ``n`` cycles of the SDK's awaited loop (``sdk``) or the raw loop (``raw``) after 50 warm-up cycles."""
    import asyncio

    import agentsdk.loop
    from agentsdk.bench import overhead

    agentsdk.loop.BATCH_SECONDS = float(os.environ.get("AGENTSDK_BENCH_BATCH", BATCH_UNDER_VALGRIND))
    if what == "sdk":
        asyncio.run(overhead._sdk_wave("mujoco", robot, 50, n))
    else:
        sim = overhead.RawMujoco(overhead.load_robot(robot))
        q0 = sim.positions()
        sim.run_wave(q0, 0, 50)
        sim.run_wave(q0, 50, n)


def _instructions(valgrind: str, what: str, n: int, robot: str) -> int:
    """Instructions valgrind counted in a child running ``n`` cycles."""
    env = {**os.environ, "PYTHONHASHSEED": "0", "OPENBLAS_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory(prefix="agentsdk-cg-") as tmp:
        cmd = [valgrind, "--tool=cachegrind", "--cache-sim=no", f"--cachegrind-out-file={tmp}/cg.out",
               sys.executable, "-m", "agentsdk.bench.instructions", "--child", what, str(n), robot]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600, check=False)
    found = re.search(r"I\s+refs:\s+([\d,]+)", proc.stderr)
    if proc.returncode != 0 or found is None:
        tail = "\n".join(proc.stderr.splitlines()[-12:])
        raise RuntimeError(f"valgrind run of {what} {robot} ({n} cycles) failed ({proc.returncode}):\n{tail}")
    return int(found.group(1).replace(",", ""))


def per_cycle(valgrind: str, what: str, robot: str, short: int, long: int) -> float:
    """Instructions per cycle: the difference of a long and a short run (both at once: one per core)."""
    with ThreadPoolExecutor(2) as pool:
        a, b = pool.map(lambda n: _instructions(valgrind, what, n, robot), (short, long))
    return (b - a) / (long - short)


def _valgrind(setup: bool) -> str | None:
    found = shutil.which("valgrind")
    if found is None and setup and os.geteuid() == 0 and shutil.which("apt-get"):
        progress("instructions: installing valgrind (apt-get)")
        for cmd in (["apt-get", "install", "-y", "-q", "--no-install-recommends", "valgrind"],
                    ["apt-get", "update", "-q"],
                    ["apt-get", "install", "-y", "-q", "--no-install-recommends", "valgrind"]):
            if subprocess.run(cmd, capture_output=True, check=False).returncode == 0 and shutil.which("valgrind"):
                break
        found = shutil.which("valgrind")
    return found


def run(quick: bool = False, robots: tuple[str, ...] = ROBOTS, setup: bool = False) -> Section:
    """The awaited cycle's instructions ÷ the raw loop's, per robot (``quick``: fewer cycles, arm3 only)."""
    title = "one awaited command per tick (read + command + sleep), MuJoCo: instructions per cycle vs the raw loop"
    valgrind = _valgrind(setup)
    if valgrind is None:
        return Section("instructions", title, status="skipped",
                       notes=["valgrind is not installed (apt-get install valgrind): nothing measured"])
    short, long = (100, 600) if quick else (100, 1100)
    section = Section("instructions", title)
    for robot in robots[:1] if quick else robots:
        progress(f"instructions: {robot}, the raw loop and the SDK, {short} and {long} cycles under cachegrind")
        raw = per_cycle(valgrind, "raw", robot, short, long)
        sdk = per_cycle(valgrind, "sdk", robot, short, long)
        section.comparisons.append(Comparison(
            f"{robot} / MuJoCo: one awaited command per tick", "instructions", raw, sdk, ratio_target=TARGET,
            note="cachegrind; (I(long) - I(short)) / cycles"))
        section.data[robot] = {"raw": raw, "sdk": sdk, "ratio": sdk / raw, "cycles": [short, long]}
    section.notes.append(f"batch_seconds {BATCH_UNDER_VALGRIND * 1e3:g} ms under valgrind (~50x slower: about the "
                         "native ticks per lease of the default 1 ms)")
    section.notes.append("instructions, not time: the SDK's run at a lower rate than the raw loop's (interpreter, "
                         "ufunc dispatch), so its time ratio (--only overhead) is higher")
    return section


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", nargs=3, metavar=("WHAT", "N", "ROBOT"), help=argparse.SUPPRESS)
    parser.add_argument("--robot", action="append", choices=ROBOTS)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    if args.child:
        what, n, robot = args.child
        _child(what, int(n), robot)
        return
    print(run(args.quick, tuple(args.robot or ROBOTS), setup=True).render())


if __name__ == "__main__":
    main()
