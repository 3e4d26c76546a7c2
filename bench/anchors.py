"""The anchors: what users would pick instead, measured the same way as agentsdk, in the same run.

Every row is *time per environment step ÷ a raw ``mj_step`` loop on the same model at the same
frame skip*, both measured here, interleaved, median of the repeats:

* raw ``mj_step``: the cheapest Python loop on that very ``MjModel`` (a fresh ``MjData`` at the
  environment's state): per step ``data.ctrl[:] = u; mujoco.mj_step(model, data, nstep=frame_skip)``
  with the same control sequence;
* gymnasium (``pip install agentsdk[bench]``): ``env.step(a)`` of ``gym.make(...)`` with the
  wrappers users get (``TimeLimit`` lifted so no reset falls into the timing), Reacher-v5 and
  Pusher-v5 at frame skip 1 and at their default frame skip;
* dm_control: ``env.step(a)`` of ``suite.load(...)``, reacher-easy, cheetah-run, humanoid-walk at
  their own control step (``n_sub_steps`` physics steps per env step). dm_control runs only with a
  MuJoCo whose bindings it knows: where it does not import or load (e.g. dm_control 1.0.x on
  MuJoCo 4), the rows say so and why;
* agentsdk: arm3 and humanoid in lockstep on MuJoCo, holding a pose (one command, then
  ``clock.sleep``) and tracking a planned trajectory (``robot.follow``), as a plain ``connect``
  runs them: with block lockstep (the default since issue 28; uneventful ticks run as blocks, bit
  for bit tick by tick; ``bench/block.py`` measures it against tick by tick): wall time per control
  tick ÷ the raw loop on the backend's own compiled model at the backend's frame skip (physics
  steps per control period), with the same servo setpoints.

Random actions are drawn once per environment from a fixed seed (uniform within the action
bounds); ratios, not absolute times, compare across machines.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import math
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agentsdk.bench.common import Comparison, Section, Table, fmt, median, progress, spread

#: (environment id, frame skips to run: 1 and the environment's default)
GYM_ENVS: tuple[tuple[str, tuple[int | None, ...]], ...] = (
    ("Reacher-v5", (1, None)),
    ("Pusher-v5", (1, None)),
)
DM_TASKS: tuple[tuple[str, str], ...] = (("reacher", "easy"), ("cheetah", "run"), ("humanoid", "walk"))
AGENTSDK_ROBOTS = ("arm3", "humanoid")
UNIT = "µs/step"


@dataclass
class Row:
    """One anchor: time per env step beside the raw ``mj_step`` loop on the same model."""

    stack: str
    env: str
    frame_skip: int
    env_us: list[float] = field(default_factory=list)
    raw_us: list[float] = field(default_factory=list)
    error: str = ""

    @property
    def ratio(self) -> float:
        return median(self.env_us) / median(self.raw_us) if self.env_us and self.raw_us else math.nan


def _raw_loop(model: Any, data: Any, ctrls: np.ndarray, nstep: int) -> float:
    """Wall seconds per step of the cheapest Python loop: write ctrl, ``mj_step(nstep)``."""
    import mujoco

    step = mujoco.mj_step
    ctrl = data.ctrl
    t0 = time.perf_counter()
    for u in ctrls:
        ctrl[:] = u
        step(model, data, nstep=nstep)
    return (time.perf_counter() - t0) / len(ctrls)


def _fresh_data(model: Any, data: Any) -> Any:
    """A new ``MjData`` at ``data``'s full state (so the raw loop starts where the environment did)."""
    import mujoco

    d = mujoco.MjData(model)
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    mujoco.mj_setState(model, d, state, spec)
    mujoco.mj_forward(model, d)
    return d


def _actions(low: np.ndarray, high: np.ndarray, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    low = np.where(np.isfinite(low), low, -1.0)
    high = np.where(np.isfinite(high), high, 1.0)
    return low + (high - low) * rng.random((n, len(low)))


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0][:200]


# --------------------------------------------------------------------------- gymnasium


def _gym_rows(steps: int, repeats: int) -> tuple[list[Row], str]:
    try:
        import gymnasium as gym
    except ImportError as exc:
        return [], f"gymnasium is not installed ({_why(exc)}): pip install 'agentsdk[bench]'"
    version = importlib.metadata.version("gymnasium")
    rows: list[Row] = []
    for env_id, skips in GYM_ENVS:
        for skip in skips:
            kwargs: dict[str, Any] = {"max_episode_steps": 10**9}
            if skip is not None:
                kwargs["frame_skip"] = skip
            try:
                env = gym.make(env_id, **kwargs)
            except Exception as exc:  # a missing extra (gymnasium[mujoco]) or an unknown id
                rows.append(Row("gymnasium", env_id, skip or 0, error=_why(exc)))
                continue
            try:
                base = env.unwrapped
                fs = int(base.frame_skip)
                row = Row("gymnasium", env_id, fs)
                label = f"{env_id}{' (its default frame skip)' if skip is None else ''}"
                progress(f"anchors: gymnasium {label}, {repeats} x {steps} steps")
                space = env.action_space
                acts = _actions(space.low, space.high, steps, seed=1).astype(space.dtype)
                env.reset(seed=0)
                for a in acts[: min(200, steps)]:  # warm-up (and the env checker's first-call checks)
                    env.step(a)
                for _ in range(repeats):
                    d = _fresh_data(base.model, base.data)
                    row.raw_us.append(_raw_loop(base.model, d, acts.astype(np.float64), fs) * 1e6)
                    step = env.step
                    t0 = time.perf_counter()
                    for a in acts:
                        step(a)
                    row.env_us.append((time.perf_counter() - t0) / steps * 1e6)
                rows.append(row)
                row.env = label
            finally:
                env.close()
    return rows, f"gymnasium {version}"


# --------------------------------------------------------------------------- dm_control


def _dm_rows(steps: int, repeats: int) -> tuple[list[Row], str]:
    os.environ.setdefault("MUJOCO_GL", "disable")  # no renderer: nothing here draws
    try:
        version = importlib.metadata.version("dm-control")
    except importlib.metadata.PackageNotFoundError:
        return [], "dm_control is not installed: pip install 'agentsdk[bench]'"
    import mujoco

    where = f"dm_control {version} with MuJoCo {mujoco.__version__}"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from dm_control import suite
    except Exception as exc:
        return [Row("dm_control", f"{d}-{t}", 0, error=f"{where}: import failed: {_why(exc)}") for d, t in DM_TASKS], (
            where
        )
    rows: list[Row] = []
    for domain, task in DM_TASKS:
        name = f"{domain}-{task}"
        try:
            env = suite.load(domain, task, task_kwargs={"random": 0})
        except Exception as exc:  # dm_control's bindings index fields this MuJoCo no longer has
            rows.append(Row("dm_control", name, 0, error=f"{where} cannot load it: {_why(exc)}"))
            continue
        try:
            fs = round(env.control_timestep() / env.physics.timestep())
            row = Row("dm_control", name, fs)
            progress(f"anchors: dm_control {name} (frame skip {fs}), {repeats} x {steps} steps")
            spec = env.action_spec()
            acts = _actions(spec.minimum, spec.maximum, steps, seed=1)
            env.reset()
            model, data = env.physics.model.ptr, env.physics.data.ptr
            for a in acts[: min(200, steps)]:
                env.step(a)
            for _ in range(repeats):
                d = _fresh_data(model, data)
                row.raw_us.append(_raw_loop(model, d, acts, fs) * 1e6)
                step = env.step
                t0 = time.perf_counter()
                k = 0
                while k < steps:  # dm_control episodes end (1000 steps): resets stay out of the timing
                    ts = step(acts[k])
                    k += 1
                    if ts.last():
                        dt = time.perf_counter() - t0
                        env.reset()
                        t0 = time.perf_counter() - dt
                row.env_us.append((time.perf_counter() - t0) / steps * 1e6)
            rows.append(row)
        finally:
            with contextlib.suppress(Exception):
                env.close()
    return rows, where


# --------------------------------------------------------------------------- agentsdk


def _agentsdk_rows(sim_s: float, repeats: int) -> list[Row]:
    from agentsdk.bench import overhead as ov
    from agentsdk.trajectory import TrajectorySampler

    rows: list[Row] = []
    for robot in AGENTSDK_ROBOTS:
        rb = ov.load_robot(robot)
        _wps, traj = ov.waypoints(rb, sim_s)
        raw = ov.RawMujoco(rb)
        q_init = raw.positions()
        nsub = raw.nsub
        ticks_track = round((traj.duration + 0.2) / rb.period)
        ticks_hold = round(sim_s / rb.period)
        sampler = TrajectorySampler(traj, 0.0, q_init, np.zeros(len(q_init)), np.zeros(len(q_init)))
        track_ctrl = np.empty((ticks_track, len(q_init)))
        for k in range(ticks_track):
            q, v, _a = sampler.sample(k * rb.period)
            track_ctrl[k] = rb.kp * q + rb.kd * v  # the servo law's ctrl (gain 1, bias -kp q - kd v)
        hold_ctrl = np.repeat((rb.kp * q_init)[None, :], ticks_hold, axis=0)
        hold = Row("agentsdk", f"{robot} lockstep (blocks, the default), holding a pose", nsub)
        track = Row("agentsdk", f"{robot} lockstep (blocks, the default), follow() a trajectory", nsub)
        progress(f"anchors: agentsdk {robot} (frame skip {nsub}), hold {sim_s:g} s and track "
                 f"{traj.duration + 0.2:.1f} s, x {repeats}")
        for _ in range(repeats):
            for row, ctrls in ((hold, hold_ctrl), (track, track_ctrl)):
                sim = ov.RawMujoco(rb)
                sim.data.ctrl[:] = ctrls[0]
                row.raw_us.append(_raw_loop(sim.model, sim.data, ctrls, nsub) * 1e6)
            s, w = ov.run_sdk(f"anchors {robot} hold", ov.sdk_hold, "mujoco", robot, sim_s)
            hold.env_us.append(w / (s / rb.period) * 1e6)
            s, w, _code, _q = ov.run_sdk(f"anchors {robot} track", ov.sdk_track, "mujoco", robot, traj, 0.2)
            track.env_us.append(w / (s / rb.period) * 1e6)
        rows += [hold, track]
    return rows


# --------------------------------------------------------------------------- section


def run(quick: bool = False) -> Section:
    steps = 1000 if quick else 4000
    repeats = 3 if quick else 5
    sim_s = 1.0 if quick else 3.0
    sec = Section(
        "anchors",
        "time per env step ÷ raw mj_step on the same model and frame skip: agentsdk, gymnasium, dm_control",
    )
    notes: list[str] = []

    def gym_() -> list[Row]:
        rows, what = _gym_rows(steps, repeats)
        notes.append(what)
        return rows

    def dm_() -> list[Row]:
        rows, what = _dm_rows(steps, repeats)
        notes.append(what)
        return rows

    runners: list[tuple[str, Callable[[], list[Row]]]] = [
        ("agentsdk", lambda: _agentsdk_rows(sim_s, repeats)),
        ("gymnasium", gym_),
        ("dm_control", dm_),
    ]
    rows: list[Row] = []
    for stack, fn in runners:
        try:
            rows += fn()
        except Exception as exc:  # one stack failing leaves the others' rows
            rows.append(Row(stack, "(all)", 0, error=_why(exc)))
    for r in rows:
        if r.error:
            sec.notes.append(f"{r.stack} {r.env}: not measured: {r.error}")
            continue
        sec.comparisons.append(
            Comparison(
                f"{r.stack} {r.env}, frame skip {r.frame_skip}: time per step",
                UNIT,
                median(r.raw_us),
                median(r.env_us),
                baseline_label="raw mj_step",
                sdk_label=r.stack,
                extra={"raw_us": spread(r.raw_us), "env_us": spread(r.env_us)},
            )
        )
    measured = sorted((r for r in rows if not r.error), key=lambda r: r.ratio)
    sec.tables.append(
        Table(
            "ranked by ratio (env step ÷ raw mj_step of the same model, same frame skip, same run)",
            ("stack", "environment", "frame skip", "raw µs/step", "env µs/step", "ratio"),
            [
                [r.stack, r.env, r.frame_skip, fmt(median(r.raw_us)), fmt(median(r.env_us)), f"{r.ratio:.2f}x"]
                for r in measured
            ],
        )
    )
    sec.data["rows"] = [
        {"stack": r.stack, "env": r.env, "frame_skip": r.frame_skip, "raw_us": r.raw_us, "env_us": r.env_us,
         "ratio": r.ratio, "error": r.error}
        for r in rows
    ]
    sec.notes += [f"versions: {n}" for n in notes if n]
    sec.notes.append(
        "raw mj_step = `data.ctrl[:] = u; mj_step(model, data, nstep=frame_skip)` on the environment's own model "
        "(a fresh MjData at its state), the same controls; agentsdk's frame skip is physics steps per control "
        "period of the robot. Same controls, same model: the ratio is what the stack adds around the physics."
    )
    sec.notes.append(
        "agentsdk rows: a plain connect, so block lockstep is on (the default in MuJoCo lockstep): holds and "
        "trajectory stretches run as blocks of up to 256 ticks; `--only block` compares it with tick by tick."
    )
    return sec


if __name__ == "__main__":
    import sys

    print(run("--quick" in sys.argv).render())
