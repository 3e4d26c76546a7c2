"""The anchors: what users would pick instead, measured the same way as agentsdk, in the same run.

Every row is *CPU time of the stepping thread per environment step ÷ a raw ``mj_step`` loop on the
same model at the same frame skip* (frame skip = physics steps per control/env step), both measured
here with ``time.thread_time`` (robust to other load on the machine, unlike wall time, which is kept
as a secondary column), raw and env repeats interleaved (the order flips every repeat), the ratio
the median of the repeats' ratios, and the raw baseline printed beside it:

* raw ``mj_step``: the cheapest Python loop on that very ``MjModel`` (a fresh ``MjData`` at the
  environment's state): per step ``data.ctrl[:] = u; mujoco.mj_step(model, data, nstep=frame_skip)``
  with the same control sequence;
* gymnasium (``pip install agentsdk[bench]``): ``env.step(a)`` of ``gym.make(...)`` with the
  wrappers users get (``TimeLimit`` lifted so no reset falls into the timing), Reacher-v5 and
  Pusher-v5 at frame skip 1 and at their default frame skip (2 and 5), in this process on the
  installed MuJoCo;
* dm_control: ``env.step(a)`` of ``suite.load(...)``, reacher-easy, cheetah-run (frame skip 1) and
  humanoid-walk (5) at their own control step. dm_control 1.0.50, the newest, requires
  ``mujoco>=3.17`` and cannot load a suite model on MuJoCo 4 (its bindings index
  ``MjModel.flex_vertedge``, which MuJoCo 4 removed; no flag avoids it). So these rows run in a
  separate interpreter: a virtual environment with dm_control and the MuJoCo it supports, pinned in
  ``bench/anchors-dm_control.txt``, under ``$XDG_CACHE_HOME/agentsdk/bench-dm_control`` (default
  ``~/.cache``), created with pip when the anchors are asked for by name (``agentsdk bench --only
  anchors``; about 500 MB, half a minute) and reused after (rebuilt when the pinned file changes).
  Both the raw loop and the env run there (``bench/peers.py`` as a script, one JSON line per row),
  so the ratio compares like with like. ``AGENTSDK_BENCH_DM_PYTHON=/path/to/python`` uses another
  interpreter that has dm_control instead. Where none can be had (pip unreachable, the full bench
  without the environment set up yet) the rows say "cannot run" and why;
* agentsdk: arm3 and humanoid in lockstep on MuJoCo, holding a pose (one command, then
  ``clock.sleep``) and tracking a planned trajectory (``robot.follow``), as a plain ``connect``
  runs them (block lockstep, the default: uneventful ticks run as blocks, bit for bit tick by tick;
  ``bench/block.py`` measures it against tick by tick), at every frame skip a peer row has (1, 2, 5:
  ``update_rate`` 1000, 500 (the robots' own), 200 Hz on their 1 ms physics step): CPU per control
  tick ÷ the raw loop on the backend's own compiled model at the same frame skip, with the servo
  law's controls for the same setpoints. The ``follow()`` call itself (once per motion, before its
  first tick) is timed apart and reported in a note, as gymnasium's and dm_control's resets are
  left out. Each agentsdk row ends with its verdict: below every gymnasium and dm_control row at
  the same frame skip, or not, and the lowest ("worst") peer ratio there.

Random actions are drawn once per environment from a fixed seed (uniform within the action
bounds); ratios, not absolute times, compare across machines.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from agentsdk.bench.common import Comparison, Section, Table, fmt, median, progress, spread
from agentsdk.bench.peers import DM_TASKS, PeerRow, Timing, gym_rows, interleave, parse_output, raw_loop, why

Row = PeerRow

AGENTSDK_ROBOTS = ("arm3", "humanoid")
#: the frame skips agentsdk runs at: every frame skip of a peer row (gymnasium at 1 and its defaults 2 and 5,
#: dm_control reacher/cheetah 1, humanoid 5); 2 is the robots' own (500 Hz on a 1 ms physics step)
AGENTSDK_FRAME_SKIPS = (1, 2, 5)
#: dm_control's frame skips (control step ÷ physics step), for the rows that cannot run
DM_FRAME_SKIPS = {"reacher-easy": 1, "cheetah-run": 1, "humanoid-walk": 5}
#: gymnasium's rows and frame skips (Reacher-v5's default is 2, Pusher-v5's 5), for the rows that cannot run
GYM_FRAME_SKIPS = {"Reacher-v5": 1, "Reacher-v5 (its default)": 2, "Pusher-v5": 1, "Pusher-v5 (its default)": 5}
UNIT = "µs/step"

BENCH_DIR = Path(__file__).resolve().parent
PEERS_SCRIPT = BENCH_DIR / "peers.py"
DM_REQUIREMENTS = BENCH_DIR / "anchors-dm_control.txt"
#: an interpreter with dm_control to use instead of the pinned environment
DM_PYTHON_ENV = "AGENTSDK_BENCH_DM_PYTHON"
#: seconds for pip to build the pinned environment, and for the dm_control rows to run
SETUP_TIMEOUT_S = 900.0
RUN_TIMEOUT_S = 1800.0


def ratios(row: Row, wall: bool = False) -> list[float]:
    """Each repeat's env ÷ raw (raw and env of a repeat ran back to back)."""
    env, raw = (row.env_wall_us, row.raw_wall_us) if wall else (row.env_cpu_us, row.raw_cpu_us)
    return [e / r for e, r in zip(env, raw, strict=False) if r > 0]


def ratio(row: Row, wall: bool = False) -> float:
    """The median of the repeats' ratios (NaN when the row has none)."""
    return median(ratios(row, wall))


# --------------------------------------------------------------------------- dm_control: the pinned interpreter


def dm_venv_dir() -> Path:
    """Where the pinned dm_control environment lives: ``$XDG_CACHE_HOME/agentsdk/bench-dm_control``."""
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(cache) / "agentsdk" / "bench-dm_control"


def _pin_digest() -> str:
    return hashlib.sha256(DM_REQUIREMENTS.read_bytes()).hexdigest()


def dm_python(setup: bool) -> tuple[Path | None, str]:
    """(interpreter to run the dm_control rows with, "") or (None, why it cannot run).

    ``$AGENTSDK_BENCH_DM_PYTHON`` if set; else the pinned environment, created now when ``setup``.
    """
    override = os.environ.get(DM_PYTHON_ENV)
    if override:
        p = Path(override)
        if not (p.is_file() and os.access(p, os.X_OK)):
            return None, f"{DM_PYTHON_ENV}={override} is not an executable file: point it at a python with dm_control"
        return p, ""
    venv = dm_venv_dir()
    py = venv / "bin" / "python"
    stamp = venv / "agentsdk-pins.sha256"
    digest = _pin_digest()
    if py.is_file() and stamp.is_file() and stamp.read_text(encoding="utf-8").strip() == digest:
        return py, ""
    if not setup:
        return None, (f"the pinned dm_control environment ({DM_REQUIREMENTS.name}) is not set up at {venv}: "
                      "run `agentsdk bench --only anchors` once to create it (pip, ~500 MB)")
    progress(f"anchors: creating the pinned dm_control environment at {venv} (pip, ~500 MB, once)")
    shutil.rmtree(venv, ignore_errors=True)
    try:
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True, text=True,
                       timeout=300)
        res = subprocess.run(
            [str(py), "-m", "pip", "install", "--disable-pip-version-check", "--no-input", "--quiet",
             "--retries", "2", "--timeout", "30", "-r", str(DM_REQUIREMENTS)],
            capture_output=True, text=True, timeout=SETUP_TIMEOUT_S,
        )
    except (OSError, subprocess.SubprocessError) as exc:
        shutil.rmtree(venv, ignore_errors=True)
        return None, f"could not create the pinned dm_control environment at {venv}: {why(exc)}"
    if res.returncode != 0:
        err = [ln for ln in res.stderr.splitlines() if ln.strip() and not ln.startswith("WARNING: Location")]
        shutil.rmtree(venv, ignore_errors=True)
        return None, (f"pip could not install {DM_REQUIREMENTS.name} into {venv} (is the package index reachable?): "
                      f"{err[-1] if err else f'exit {res.returncode}'}")
    stamp.write_text(digest + "\n", encoding="utf-8")
    return py, ""


def peer_rows_in(python: Path, stack: str, steps: int, repeats: int,
                 timeout: float = RUN_TIMEOUT_S) -> tuple[list[Row], str]:
    """``stack``'s rows measured by ``bench/peers.py`` under ``python`` (its own MuJoCo), and its versions line.

    An interpreter that cannot be started, fails or prints no rows gives ``([], why)``.
    """
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["MUJOCO_GL"] = "disable"
    cmd = [str(python), "-I", str(PEERS_SCRIPT), stack, "--steps", str(steps), "--repeats", str(repeats)]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except (OSError, subprocess.SubprocessError) as exc:
        return [], f"cannot run {python}: {why(exc)}"
    for line in res.stderr.splitlines():  # its progress lines, passed on
        if line.startswith("[bench "):
            print(line, file=sys.stderr, flush=True)
    rows, versions = parse_output(res.stdout)
    if res.returncode != 0 or not rows:
        tail = [ln for ln in res.stderr.splitlines() if ln.strip() and not ln.startswith("[bench ")]
        if res.returncode == 0 and versions:  # it ran and said why it has no rows
            return rows, f"{python}: {versions}"
        return rows, f"{python} exited {res.returncode}: {tail[-1] if tail else 'no rows'}"
    return rows, f"{versions} (in {python})"


def dm_control_rows(steps: int, repeats: int, setup: bool, python: Path | None = None) -> tuple[list[Row], str]:
    """dm_control's rows from its pinned interpreter (or ``python``), or rows that say why they cannot run."""
    why_not = ""
    if python is None:
        python, why_not = dm_python(setup)
    rows: list[Row] = []
    what = ""
    if python is not None:
        rows, what = peer_rows_in(python, "dm_control", steps, repeats)
        if not rows:
            why_not, what = what, ""
    if not rows:
        rows = [Row("dm_control", f"{d}-{t}", DM_FRAME_SKIPS.get(f"{d}-{t}", 0), error=f"cannot run: {why_not}")
                for d, t in DM_TASKS]
    return rows, what


# --------------------------------------------------------------------------- agentsdk


def _clocks() -> Timing:
    return time.thread_time(), time.perf_counter()


async def _sdk_hold(robot: str, rate: float, sim_s: float) -> Timing:
    """Per-tick (CPU of this thread, wall) seconds of holding the initial pose for ``sim_s``."""
    import agentsdk
    from agentsdk import JointCommand
    from agentsdk.bench import overhead as ov

    async with agentsdk.connect("mujoco", robot, update_rate=rate) as r:
        await r.command(JointCommand("position", (await r.read()).position.tolist()))
        await r.clock.sleep(0.2)  # the command's ramp has ended: a plain hold
        n0 = r.ticks
        c0, w0 = _clocks()
        await r.clock.sleep(sim_s)
        c1, w1 = _clocks()
        n = max(r.ticks - n0, 1)
        ov.check_stall(r, f"anchors {robot} hold")
        return (c1 - c0) / n, (w1 - w0) / n


async def _sdk_track(robot: str, rate: float, traj: Any, tail: float, calls: list[float]) -> Timing:
    """Per-tick (CPU of this thread, wall) seconds of following ``traj`` (planned beforehand) and ``tail`` after.

    The ``follow()`` call itself (its checks of the trajectory, once per motion, before the first tick) is
    timed apart: its CPU seconds are appended to ``calls``.
    """
    import agentsdk
    from agentsdk.bench import overhead as ov

    async with agentsdk.connect("mujoco", robot, update_rate=rate) as r:
        c = time.thread_time()
        motion = r.follow(traj)
        calls.append(time.thread_time() - c)
        n0 = r.ticks
        c0, w0 = _clocks()
        await r.clock.sleep(traj.duration + tail)
        c1, w1 = _clocks()
        n = max(r.ticks - n0, 1)
        ov.check_stall(r, f"anchors {robot} track")
        if not motion.done():
            raise RuntimeError(f"anchors {robot} track at {rate:g} Hz: the motion had not ended after its duration")
        return (c1 - c0) / n, (w1 - w0) / n


def _agentsdk_rows(sim_s: float, repeats: int, follow_calls: dict[str, list[float]],
                   frame_skips: tuple[int, ...] = AGENTSDK_FRAME_SKIPS) -> list[Row]:
    """agentsdk's rows; the CPU seconds of each ``follow()`` call go to ``follow_calls[robot]``."""
    from agentsdk.bench import overhead as ov
    from agentsdk.trajectory import TrajectorySampler

    tail = 0.2
    rows: list[Row] = []
    for robot in AGENTSDK_ROBOTS:
        rb0 = ov.load_robot(robot)
        _wps, traj = ov.waypoints(rb0, sim_s)
        dt = _physics_step(rb0)
        for fs in frame_skips:
            rate = round(1.0 / (fs * dt), 6)
            rb = dataclasses.replace(rb0, config=rb0.config.with_update_rate(rate), period=1.0 / rate)
            probe = ov.RawMujoco(rb)
            if probe.nsub != fs:
                raise RuntimeError(f"{robot} at {rate:g} Hz runs {probe.nsub} physics steps per tick, not {fs}")
            q_init = probe.positions()
            ticks_track = round((traj.duration + tail) / rb.period)
            ticks_hold = round(sim_s / rb.period)
            zeros = np.zeros(len(q_init))
            sampler = TrajectorySampler(traj, 0.0, q_init, zeros, zeros)
            track_ctrl = np.empty((ticks_track, len(q_init)))
            for k in range(ticks_track):
                q, v, _a = sampler.sample(k * rb.period)
                track_ctrl[k] = rb.kp * q + rb.kd * v  # the servo law's ctrl (gain 1, bias -kp q - kd v)
            hold_ctrl = np.repeat((rb.kp * q_init)[None, :], ticks_hold, axis=0)
            progress(f"anchors: agentsdk {robot} at frame skip {fs} ({rate:g} Hz), hold {sim_s:g} s and track "
                     f"{traj.duration + tail:.1f} s, x {repeats}")

            def raw(ctrls: np.ndarray, rb: Any = rb) -> Callable[[], Timing]:
                def run() -> Timing:
                    sim = ov.RawMujoco(rb)
                    sim.data.ctrl[:] = ctrls[0]
                    return raw_loop(sim.model, sim.data, ctrls, sim.nsub)

                return run

            label = f"{robot} {rate:g} Hz"
            calls = follow_calls.setdefault(robot, [])

            def sdk(what: str, fn: Any, *args: Any) -> Callable[[], Timing]:
                return lambda: ov.run_sdk(f"anchors {what}", fn, *args)

            hold = interleave(Row("agentsdk", f"{label} hold", fs), repeats, raw(hold_ctrl),
                              sdk(f"{robot} hold", _sdk_hold, robot, rate, sim_s))
            track = interleave(Row("agentsdk", f"{label} follow()", fs), repeats, raw(track_ctrl),
                               sdk(f"{robot} track", _sdk_track, robot, rate, traj, tail, calls))
            rows += [hold, track]
    return rows


def _physics_step(rb: Any) -> float:
    """The robot's MuJoCo physics timestep (robot.yaml ``backends.mujoco.timestep``, else the backend default)."""
    from agentsdk.bench import overhead as ov

    return float(ov.RawMujoco(rb).model.opt.timestep)


# --------------------------------------------------------------------------- verdicts


def verdicts(rows: list[Row]) -> list[Comparison]:
    """Per agentsdk row: below every measured gymnasium and dm_control row at the same frame skip, or not."""
    peers = [r for r in rows if r.stack != "agentsdk"]
    out: list[Comparison] = []
    for a in rows:
        if a.stack != "agentsdk" or a.error:
            continue
        same = [p for p in peers if p.frame_skip == a.frame_skip and not p.error]
        missing = [f"{p.stack} {p.env}" for p in peers if p.error and p.frame_skip in (a.frame_skip, 0)]
        mine = ratio(a)
        if not same:
            out.append(Comparison(
                f"agentsdk {a.env}, frame skip {a.frame_skip}: below every gymnasium and dm_control row at the same "
                "frame skip: no peer row measured there", "× raw", None, mine,
                note="; ".join(f"not measured: {m}" for m in missing)))
            continue
        worst = min(same, key=ratio)  # the hardest to beat: the lowest peer ratio
        below = all(mine < ratio(p) for p in same)
        note = f"compared with {len(same)} peer row(s): " + ", ".join(
            f"{p.stack} {p.env} {ratio(p):.2f}x" for p in sorted(same, key=ratio))
        if missing:
            note += "; not measured: " + ", ".join(missing)
        out.append(Comparison(
            f"agentsdk {a.env}, frame skip {a.frame_skip}: below every gymnasium and dm_control row at the same "
            f"frame skip: {'yes' if below else 'no'} (worst peer ratio {ratio(worst):.2f}x: {worst.env}"
            + (f"; {len(missing)} peer row(s) not measured)" if missing else ")"),
            "× raw", ratio(worst), mine, baseline_label="lowest peer ratio", sdk_label="agentsdk ratio",
            ratio_target=1.0, note=note))
    return out


def comparability(rows: list[Row]) -> list[str]:
    """Which peer rows are comparable with which agentsdk rows (one line per frame skip)."""
    out = []
    for fs in sorted({r.frame_skip for r in rows if r.frame_skip}):
        ours = [r.env for r in rows if r.stack == "agentsdk" and r.frame_skip == fs]
        theirs = [f"{r.stack} {r.env}{' (not measured)' if r.error else ''}"
                  for r in rows if r.stack != "agentsdk" and r.frame_skip == fs]
        out.append(f"frame skip {fs}: agentsdk [{'; '.join(ours) or 'none'}] vs [{'; '.join(theirs) or 'none'}]")
    return out


# --------------------------------------------------------------------------- section


def _range(vals: list[float]) -> str:
    return f"{min(vals):.2f}-{max(vals):.2f}" if vals else "-"


def run(quick: bool = False, setup: bool = False) -> Section:
    """The anchors section; ``setup`` lets it create the pinned dm_control environment (pip) when missing."""
    steps = 1000 if quick else 4000
    repeats = 3 if quick else 5
    sim_s = 1.0 if quick else 3.0
    sec = Section(
        "anchors",
        "CPU per env step ÷ raw mj_step on the same model and frame skip, same run: agentsdk, gymnasium, dm_control",
    )
    notes: list[str] = []
    follow_calls: dict[str, list[float]] = {}

    def gym_() -> list[Row]:
        rows, what = gym_rows(steps, repeats)
        notes.append(what)
        # not installed: a row per environment that says so (the verdicts name what they were not compared with)
        return rows or [Row("gymnasium", env, fs, error=f"cannot run: {what}") for env, fs in GYM_FRAME_SKIPS.items()]

    def dm_() -> list[Row]:
        rows, what = dm_control_rows(steps, repeats, setup)
        notes.append(what)
        return rows

    runners: list[tuple[str, Callable[[], list[Row]]]] = [
        ("gymnasium", gym_),
        ("dm_control", dm_),
        ("agentsdk", lambda: _agentsdk_rows(sim_s, repeats, follow_calls)),
    ]
    rows: list[Row] = []
    for stack, fn in runners:
        try:
            rows += fn()
        except Exception as exc:  # one stack failing leaves the others' rows
            rows.append(Row(stack, "(all)", 0, error=why(exc)))
    for r in rows:
        if r.error:
            sec.notes.append(f"{r.stack} {r.env}: not measured: {r.error}")
        elif r.stack != "agentsdk":
            sec.comparisons.append(Comparison(
                f"{r.stack} {r.env}, frame skip {r.frame_skip}: CPU per step ÷ raw", UNIT, median(r.raw_cpu_us),
                median(r.env_cpu_us), baseline_label="raw mj_step", sdk_label=r.stack,
                extra={"ratio_median_of_repeats": ratio(r), "raw_cpu_us": spread(r.raw_cpu_us),
                       "env_cpu_us": spread(r.env_cpu_us)}))
    sec.comparisons += verdicts(rows)
    measured = sorted((r for r in rows if not r.error), key=lambda r: (r.frame_skip, ratio(r)))
    sec.tables.append(Table(
        "by frame skip, then ratio: CPU of the stepping thread per env step ÷ the raw mj_step loop on the same model "
        f"and frame skip, median of {repeats} interleaved repeats (range over the repeats); wall-time ratio beside",
        ("stack", "environment", "frame skip", "raw CPU µs/step", "env CPU µs/step", "ratio (CPU)", "range",
         "ratio (wall)"),
        [[r.stack, r.env, r.frame_skip, fmt(median(r.raw_cpu_us)), fmt(median(r.env_cpu_us)), f"{ratio(r):.2f}x",
          _range(ratios(r)), f"{ratio(r, wall=True):.2f}x"] for r in measured],
    ))
    sec.data["rows"] = [{**dataclasses.asdict(r), "ratio_cpu": ratio(r), "ratio_wall": ratio(r, wall=True)}
                        for r in rows]
    sec.notes += [f"versions: {n}" for n in notes if n]
    sec.notes += ["comparable rows (frame skip = physics steps per control/env step): " + line
                  for line in comparability(rows)]
    sec.notes.append(
        "raw mj_step = `data.ctrl[:] = u; mj_step(model, data, nstep=frame_skip)` on the environment's own model "
        "(a fresh MjData at its state) with the same controls, on the same interpreter and MuJoCo as the env "
        "(dm_control: in its pinned environment); CPU = time.thread_time of the stepping thread (agentsdk: the "
        "event loop's, which steps the physics in lockstep); ratio = median over the repeats of env ÷ raw of the "
        "same repeat."
    )
    sec.notes.append(
        "agentsdk rows: a plain connect (block lockstep on, the default) with update_rate set so that a control "
        f"tick is {', '.join(map(str, AGENTSDK_FRAME_SKIPS))} physics steps of 1 ms (hold: a position command, then "
        "clock.sleep; follow(): a pre-planned trajectory and 0.2 s after it)."
    )
    if follow_calls:
        sec.data["follow_call_cpu_ms"] = {k: [v * 1e3 for v in vals] for k, vals in follow_calls.items()}
        sec.notes.append(
            "not in the follow() rows: the follow() call itself, once per motion before its first tick (checks of the "
            "pre-planned trajectory), CPU median " + ", ".join(
                f"{k} {median(v) * 1e3:.1f} ms" for k, v in follow_calls.items() if v)
            + " per motion (gymnasium and dm_control have no motion to start; their resets are left out alike)"
        )
    if quick:
        sec.notes.append(f"quick: {repeats} repeats of {steps} env steps / {sim_s:g} s of robot time")
    return sec


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--no-setup", action="store_true", help="do not create the pinned dm_control environment")
    a = parser.parse_args()
    print(run(a.quick, setup=not a.no_setup).render())
