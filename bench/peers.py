"""The peer stacks of the anchors (gymnasium, dm_control), measured the way ``bench/anchors.py`` measures agentsdk.

This module imports only the standard library, numpy, ``mujoco`` and the peer itself, never agentsdk,
so that it also runs as a script under another interpreter: dm_control 1.0.x cannot load its suite's
models on MuJoCo 4 (its bindings index ``MjModel`` fields MuJoCo 4 removed), so ``bench/anchors.py``
runs the dm_control rows in a virtual environment pinned to the MuJoCo that dm_control release
supports (``bench/anchors-dm_control.txt``), where the raw ``mj_step`` loop runs on that same MuJoCo::

    <venv>/bin/python -I bench/peers.py dm_control --steps 4000 --repeats 5

prints one JSON object per line: first ``{"kind": "meta", "versions": "..."}``, then one
``{"kind": "row", ...}`` per environment (the fields of :class:`PeerRow`; ``error`` non-empty when
that environment could not be measured). :func:`parse_output` reads it back.

Each row is timed as *CPU time of the stepping thread* (``time.thread_time``; other processes on a
loaded machine barely move it) and wall time, per environment step, for the environment's
``env.step`` and for the cheapest raw loop on the environment's own ``MjModel`` (a fresh ``MjData``
at the environment's state; per step ``data.ctrl[:] = u; mj_step(model, data, nstep=frame_skip)``
with the same controls). Raw and env repeats alternate (the order flips every repeat), so a change
of load hits both alike.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import json
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

#: (environment id, frame skips to run: 1 and the environment's default)
GYM_ENVS: tuple[tuple[str, tuple[int | None, ...]], ...] = (
    ("Reacher-v5", (1, None)),
    ("Pusher-v5", (1, None)),
)
DM_TASKS: tuple[tuple[str, str], ...] = (("reacher", "easy"), ("cheetah", "run"), ("humanoid", "walk"))


@dataclass
class PeerRow:
    """One environment (or agentsdk run): per-step CPU and wall time of it and of the raw loop, per repeat (µs)."""

    stack: str
    env: str
    frame_skip: int
    raw_cpu_us: list[float] = field(default_factory=list)
    env_cpu_us: list[float] = field(default_factory=list)
    raw_wall_us: list[float] = field(default_factory=list)
    env_wall_us: list[float] = field(default_factory=list)
    error: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"kind": "row", **asdict(self)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> PeerRow:
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


Timing = tuple[float, float]  # (thread CPU seconds, wall seconds)


def _clocks() -> Timing:
    return time.thread_time(), time.perf_counter()


def interleave(row: PeerRow, repeats: int, raw: Callable[[], Timing], env: Callable[[], Timing]) -> PeerRow:
    """``repeats`` rounds of ``raw()`` and ``env()`` (each: per-step CPU and wall seconds), alternating order."""
    for k in range(repeats):
        for which in (("raw", "env") if k % 2 == 0 else ("env", "raw")):
            cpu, wall = raw() if which == "raw" else env()
            if which == "raw":
                row.raw_cpu_us.append(cpu * 1e6)
                row.raw_wall_us.append(wall * 1e6)
            else:
                row.env_cpu_us.append(cpu * 1e6)
                row.env_wall_us.append(wall * 1e6)
    return row


def raw_loop(model: Any, data: Any, ctrls: np.ndarray, nstep: int) -> Timing:
    """Per-step (CPU, wall) seconds of the cheapest Python loop: write ctrl, ``mj_step(nstep)``."""
    import mujoco

    step = mujoco.mj_step
    ctrl = data.ctrl
    c0, w0 = _clocks()
    for u in ctrls:
        ctrl[:] = u
        step(model, data, nstep=nstep)
    c1, w1 = _clocks()
    return (c1 - c0) / len(ctrls), (w1 - w0) / len(ctrls)


def fresh_data(model: Any, data: Any) -> Any:
    """A new ``MjData`` at ``data``'s full state (so the raw loop starts where the environment did)."""
    import mujoco

    d = mujoco.MjData(model)
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    mujoco.mj_setState(model, d, state, spec)
    mujoco.mj_forward(model, d)
    return d


def actions(low: np.ndarray, high: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` uniform random actions within the bounds (unbounded sides: ±1), from a fixed seed."""
    rng = np.random.default_rng(seed)
    low = np.where(np.isfinite(low), low, -1.0)
    high = np.where(np.isfinite(high), high, 1.0)
    return np.asarray(low + (high - low) * rng.random((n, len(low))))


def why(exc: BaseException) -> str:
    """One line naming an exception (for a row that could not be measured)."""
    return f"{type(exc).__name__}: {exc}".splitlines()[0][:200]


def _note(msg: str) -> None:
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- gymnasium


def gym_rows(steps: int, repeats: int) -> tuple[list[PeerRow], str]:
    """gymnasium's rows (on this interpreter's MuJoCo) and a line naming the versions (or why none)."""
    try:
        import gymnasium as gym
        import mujoco
    except ImportError as exc:
        return [], f"gymnasium is not installed ({why(exc)}): pip install 'agentsdk[bench]'"
    where = f"gymnasium {importlib.metadata.version('gymnasium')} with MuJoCo {mujoco.__version__}"
    rows: list[PeerRow] = []
    for env_id, skips in GYM_ENVS:
        for skip in skips:
            kwargs: dict[str, Any] = {"max_episode_steps": 10**9}
            if skip is not None:
                kwargs["frame_skip"] = skip
            label = f"{env_id}{' (its default)' if skip is None else ''}"
            try:
                env = gym.make(env_id, **kwargs)
            except Exception as exc:  # a missing extra (gymnasium[mujoco]) or an unknown id
                rows.append(PeerRow("gymnasium", label, skip or 0, error=why(exc)))
                continue
            try:
                base = env.unwrapped
                fs = int(base.frame_skip)
                _note(f"anchors: gymnasium {label} (frame skip {fs}), {repeats} x {steps} steps")
                space = env.action_space
                acts = actions(space.low, space.high, steps, seed=1).astype(space.dtype)
                env.reset(seed=0)
                for a in acts[: min(200, steps)]:  # warm-up (and the env checker's first-call checks)
                    env.step(a)

                def raw(base: Any = base, acts: np.ndarray = acts, fs: int = fs) -> Timing:
                    return raw_loop(base.model, fresh_data(base.model, base.data), acts.astype(np.float64), fs)

                def run(env: Any = env, acts: np.ndarray = acts) -> Timing:
                    step = env.step
                    c0, w0 = _clocks()
                    for a in acts:
                        step(a)
                    c1, w1 = _clocks()
                    return (c1 - c0) / len(acts), (w1 - w0) / len(acts)

                rows.append(interleave(PeerRow("gymnasium", label, fs), repeats, raw, run))
            finally:
                env.close()
    return rows, where


# --------------------------------------------------------------------------- dm_control


def dm_rows(steps: int, repeats: int) -> tuple[list[PeerRow], str]:
    """dm_control's rows (on this interpreter's MuJoCo) and a line naming the versions (or why none)."""
    os.environ.setdefault("MUJOCO_GL", "disable")  # no renderer: nothing here draws
    try:
        version = importlib.metadata.version("dm-control")
    except importlib.metadata.PackageNotFoundError:
        return [], "dm_control is not installed in this interpreter"
    import mujoco

    where = f"dm_control {version} with MuJoCo {mujoco.__version__}"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from dm_control import suite
    except Exception as exc:
        return [PeerRow("dm_control", f"{d}-{t}", 0, error=f"{where}: import failed: {why(exc)}")
                for d, t in DM_TASKS], where
    rows: list[PeerRow] = []
    for domain, task in DM_TASKS:
        name = f"{domain}-{task}"
        try:
            env = suite.load(domain, task, task_kwargs={"random": 0})
        except Exception as exc:  # dm_control's bindings index fields this MuJoCo does not have
            rows.append(PeerRow("dm_control", name, 0, error=f"{where} cannot load it: {why(exc)}"))
            continue
        try:
            fs = round(env.control_timestep() / env.physics.timestep())
            _note(f"anchors: dm_control {name} (frame skip {fs}), {repeats} x {steps} steps")
            spec = env.action_spec()
            acts = actions(spec.minimum, spec.maximum, steps, seed=1)
            env.reset()
            model, data = env.physics.model.ptr, env.physics.data.ptr
            for a in acts[: min(200, steps)]:
                env.step(a)

            def raw(model: Any = model, data: Any = data, acts: np.ndarray = acts, fs: int = fs) -> Timing:
                return raw_loop(model, fresh_data(model, data), acts, fs)

            def run(env: Any = env, acts: np.ndarray = acts) -> Timing:
                step = env.step
                cpu = wall = 0.0
                c0, w0 = _clocks()
                for a in acts:
                    if step(a).last():  # dm_control episodes end (1000 steps): resets stay out of the timing
                        c1, w1 = _clocks()
                        cpu, wall = cpu + c1 - c0, wall + w1 - w0
                        env.reset()
                        c0, w0 = _clocks()
                c1, w1 = _clocks()
                return (cpu + c1 - c0) / len(acts), (wall + w1 - w0) / len(acts)

            rows.append(interleave(PeerRow("dm_control", name, fs), repeats, raw, run))
        finally:
            with contextlib.suppress(Exception):
                env.close()
    return rows, where


# --------------------------------------------------------------------------- the subprocess protocol

STACKS: dict[str, Callable[[int, int], tuple[list[PeerRow], str]]] = {"gymnasium": gym_rows, "dm_control": dm_rows}


def write_output(rows: Iterable[PeerRow], versions: str, out: Any) -> None:
    """The protocol: a meta line, then one JSON line per row."""
    print(json.dumps({"kind": "meta", "versions": versions}), file=out, flush=True)
    for r in rows:
        print(json.dumps(r.to_json()), file=out, flush=True)


def parse_output(text: str) -> tuple[list[PeerRow], str]:
    """The rows and the versions line of :func:`write_output`'s text (lines that are not JSON objects skipped)."""
    rows: list[PeerRow] = []
    versions = ""
    for line in text.splitlines():
        line = line.strip()
        if not line.startswith("{"):
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not isinstance(obj, dict):
            continue
        if obj.get("kind") == "meta":
            versions = str(obj.get("versions", ""))
        elif obj.get("kind") == "row":
            try:
                rows.append(PeerRow.from_json(obj))
            except TypeError:  # a row without its required fields
                continue
    return rows, versions


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stack", choices=sorted(STACKS))
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    rows, versions = STACKS[args.stack](args.steps, args.repeats)
    write_output(rows, versions, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
