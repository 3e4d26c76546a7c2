"""Load robots on simulators in child processes, so that a simulator crash cannot take the caller down.

A simulator is native code: a bad input can abort the process (PyBullet did,
on real URDFs, before the description learned to write them in order). Tools
that try many robots - ``agentsdk check``, the corpus tests - load each one in
a worker process:

* :func:`probe` connects one robot to one backend (lockstep), runs a few
  control ticks and returns a JSON-able report: joint names, the simulator's
  own view of limits, link masses and self-collision pairs
  (``simulator_report()`` of the MuJoCo and PyBullet backends), the repairs, or
  the error (type and message); with a ``behavior`` it also runs one of the
  standard trials and reports what it measured (:data:`BEHAVIORS`);
* :class:`ProbePool` keeps long-lived worker processes (``python -m
  agentsdk.probe``) that probe many robots each, in parallel; a worker that
  dies (signal, abort) or hangs is replaced, and its job reports
  ``"died": true`` with the exit status and the tail of its stderr.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import selectors
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import IO, Any

__all__ = ["BEHAVIORS", "ProbePool", "probe", "probe_in_subprocess"]

#: standard trials a probe can run after connecting (``behavior``), what the corpus tests measure:
#:
#: * ``"hold_move"``: hold the start pose for ``HOLD`` s (``drift``: the largest joint excursion), then
#:   ``move_to`` +``MOVE`` rad on every joint (clipped inside the limits; ``move_code``, ``move_error``:
#:   the result and its largest goal error), then hold ``SETTLE`` s (``final``: the positions;
#:   ``following_errors``: the following errors latched during the hold);
#: * ``"stand"``: a floating-base robot stands ``STAND`` s on its joint servos (``heights``: the base
#:   height at the start and every 0.5 s).
#: * ``"follow"``: ``agentsdk check``'s short trial: hold ``FOLLOW_HOLD`` s, ``move_to`` ±``FOLLOW_MOVE`` rad on
#:   every joint, settle ``FOLLOW_SETTLE`` s (``following_peak``/``following_window``: the largest following
#:   error per joint and its window; ``following_errors``: the following-error events; ``move_peak``: the
#:   largest error per joint while the move ran).
#: * ``"track"``: tracking in motion: after ``TRACK_HOLD`` s, a joint-space trajectory of ``TRACK`` s to
#:   +``MOVE`` rad on every joint (-``MOVE`` where + leaves the limits; ``move_code``), ``track_peak``: the
#:   largest error per joint between the servo's position setpoint and the measured position, every tick
#:   of the trajectory.
BEHAVIORS = ("hold_move", "stand", "follow", "track")
HOLD, MOVE, SETTLE, STAND = 2.0, 0.25, 0.5, 5.0
FOLLOW_HOLD, FOLLOW_MOVE, FOLLOW_SETTLE = 0.5, 0.3, 0.3
TRACK_HOLD, TRACK = 0.2, 1.0


def _jsonable(value: Any) -> Any:
    if isinstance(value, float):
        if value != value:
            return "nan"
        if value in (float("inf"), float("-inf")):
            return "inf" if value > 0 else "-inf"
        return value
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


async def _hold_move(bot: Any, out: dict[str, Any]) -> None:
    import numpy as np

    joints = bot.joints
    lower = np.array([j.lower for j in joints])
    upper = np.array([j.upper for j in joints])
    q0 = (await bot.read()).position
    out["inside_limits"] = bool(np.all((q0 >= lower - 1e-9) & (q0 <= upper + 1e-9)))
    peak = np.zeros(len(joints))
    for _ in range(round(HOLD / 0.05)):
        await bot.clock.sleep(0.05)
        peak = np.maximum(peak, np.abs((await bot.read()).position - q0))
    out["drift"] = float(peak.max(initial=0.0))
    out["drift_joint"] = joints[int(np.argmax(peak))].name if len(joints) else None
    out["following_errors"] = [e.detail for e in bot.safety.events if e.kind in ("following_error", "sensor")]
    goal = np.clip(q0 + MOVE, lower, upper)
    result = await bot.move_to({j.name: float(g) for j, g in zip(joints, goal, strict=True)})
    out["move_code"] = result.code.name
    errors = {k: abs(v) for k, v in result.error.items()}
    out["move_error"] = max(errors.values(), default=0.0)
    out["move_joint"] = max(errors, key=lambda k: errors[k]) if errors else None
    await bot.clock.sleep(SETTLE)
    out["final"] = (await bot.read()).position.tolist()
    out["goal"] = goal.tolist()


async def _follow(bot: Any, out: dict[str, Any]) -> None:
    """``agentsdk check``'s trial: hold FOLLOW_HOLD s, then a short move_to, recording the following error."""
    import numpy as np

    following = bot.safety.following
    if following is not None:
        following.reset_peak()
    joints = bot.joints
    lower = np.array([j.lower for j in joints])
    upper = np.array([j.upper for j in joints])
    try:
        await bot.clock.sleep(FOLLOW_HOLD)
        q0 = (await bot.read()).position
        goal = np.clip(q0 + np.where(q0 + FOLLOW_MOVE <= upper, FOLLOW_MOVE, -FOLLOW_MOVE), lower, upper)
        if following is not None:
            hold_peak = following.peak.copy()
            following.reset_peak()
        result = await bot.move_to({j.name: float(g) for j, g in zip(joints, goal, strict=True)})
        out["move_code"] = result.code.name
        if following is not None:
            out["move_peak"] = following.peak.tolist()
            np.fmax(following.peak, hold_peak, out=following.peak)
        await bot.clock.sleep(FOLLOW_SETTLE)
    finally:
        if following is not None:
            out["following_peak"] = following.peak.tolist()
            out["following_window"] = following.windows.tolist()
        out["following_errors"] = [e.detail for e in bot.safety.events if e.kind in ("following_error", "sensor")]


async def _track(bot: Any, out: dict[str, Any]) -> None:
    """Tracking in motion: the peak error per joint along a ``TRACK`` s joint-space trajectory."""
    import numpy as np

    following = bot.safety.following
    if following is None:
        raise ValueError("the track trial measures with the following-error check; it is off for this robot")
    joints = bot.joints
    lower = np.array([j.lower for j in joints])
    upper = np.array([j.upper for j in joints])
    await bot.clock.sleep(TRACK_HOLD)
    q0 = (await bot.read()).position
    goal = np.clip(q0 + np.where(q0 + MOVE <= upper, MOVE, -MOVE), lower, upper)
    following.reset_peak()
    result = await bot.move_to({j.name: float(g) for j, g in zip(joints, goal, strict=True)}, duration=TRACK)
    out["move_code"] = result.code.name
    out["track_peak"] = following.peak.tolist()
    out["following_errors"] = [e.detail for e in bot.safety.events if e.kind in ("following_error", "sensor")]


async def _stand(bot: Any, out: dict[str, Any]) -> None:
    heights = [bot.base_state().height]
    for _ in range(round(STAND / 0.5)):
        await bot.clock.sleep(0.5)
        heights.append(bot.base_state().height)
    out["heights"] = heights
    out["final"] = (await bot.read()).position.tolist()


async def _probe_async(
    robot: str, backend: str, duration: float, options: Mapping[str, Any], behavior: str | None = None
) -> dict[str, Any]:
    import agentsdk
    from agentsdk.errors import AgentSDKError

    async with agentsdk.connect(backend, robot=robot, **options) as bot:
        ctl = bot.backend
        desc = ctl.description
        out: dict[str, Any] = {
            "loaded": True,
            "name": desc.name,
            "format": desc.format,
            "joints": list(bot.joint_names),
            "limits": [[j.lower, j.upper, j.max_velocity, j.max_effort] for j in bot.joints],
            "repairs": [str(r) for r in desc.repairs],
        }
        report = getattr(ctl, "simulator_report", None)
        if callable(report):
            out["report"] = report()
        collision = getattr(ctl, "collision", None)
        if collision is not None:
            out["collision_repairs"] = [str(r) for r in collision.repairs]
        run_error: str | None = None
        try:
            start = await bot.read()
            out["start"] = start.position.tolist()
            await bot.clock.sleep(duration)
            state = await bot.read()
            out["position"] = state.position.tolist()
            out["gains"] = [[g.p, g.d] for g in bot.gains.values()]
            if behavior == "hold_move":
                await _hold_move(bot, out)
            elif behavior == "stand":
                await _stand(bot, out)
            elif behavior == "follow":
                await _follow(bot, out)
            elif behavior == "track":
                await _track(bot, out)
            elif behavior is not None:
                raise ValueError(f"unknown probe behavior {behavior!r}; known: {', '.join(BEHAVIORS)}")
        except AgentSDKError as exc:
            run_error = f"{type(exc).__name__}: {exc}"
        out["ok"] = run_error is None
        out["run_error"] = run_error
        out["state"] = bot.safety.state.name
        return out


def probe(
    robot: str,
    backend: str,
    *,
    duration: float = 0.02,
    options: Mapping[str, Any] | None = None,
    behavior: str | None = None,
) -> dict[str, Any]:
    """Connect ``robot`` on ``backend`` in this process, run ``duration`` s (lockstep) and report (JSON-able).

    ``loaded``: the connection opened; ``ok``: it also ran ``duration`` (and the
    ``behavior``, one of :data:`BEHAVIORS`) without a fault (``run_error`` says
    which); on failure ``error_type``/``error``.
    """
    from .errors import AgentSDKError

    t0 = time.perf_counter()
    try:
        out = asyncio.run(_probe_async(robot, backend, duration, dict(options or {}), behavior))
    except AgentSDKError as exc:
        out = {"ok": False, "loaded": False, "error_type": type(exc).__name__, "error": str(exc)}
    except Exception as exc:  # a non-SDK exception is a bug the caller must see, with its type
        out = {"ok": False, "loaded": False, "error_type": type(exc).__name__, "error": str(exc), "unexpected": True}
    out["seconds"] = time.perf_counter() - t0
    report: dict[str, Any] = _jsonable(out)
    return report


def _worker_main() -> int:
    """Worker loop: one JSON job per stdin line, one JSON result per line on the original stdout."""
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # native code printing to stdout must not corrupt the protocol
    sys.stdout = sys.stderr
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    for line in sys.stdin:
        if not line.strip():
            continue
        job = json.loads(line)
        result = probe(
            job["robot"], job["backend"], duration=job.get("duration", 0.02), options=job.get("options"),
            behavior=job.get("behavior"),
        )
        proto.write(json.dumps(result) + "\n")
    return 0


@dataclass
class _Worker:
    proc: subprocess.Popen[str]
    stderr: IO[str]
    job: int | None = None
    started: float = 0.0
    buffer: str = field(default="")


class ProbePool:
    """Long-lived probe workers; ``run(jobs)`` returns one result per job, in order.

    ``timeout`` (s) bounds one job: a worker that exceeds it is killed and
    replaced. Use as a context manager (or call ``close()``).
    """

    def __init__(self, workers: int = 2, timeout: float = 120.0, env: Mapping[str, str] | None = None) -> None:
        self.size = max(1, workers)
        self.timeout = timeout
        self.env = {**os.environ, **(env or {})}
        self._workers: list[_Worker] = []
        self.restarts = 0

    def _spawn(self) -> _Worker:
        err = tempfile.TemporaryFile("w+", encoding="utf-8", errors="replace")
        proc = subprocess.Popen(
            [sys.executable, "-m", "agentsdk.probe"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            env=self.env,
            bufsize=1,
        )
        return _Worker(proc, err)

    def __enter__(self) -> ProbePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop every worker."""
        for w in self._workers:
            self._stop(w)
        self._workers.clear()

    @staticmethod
    def _stop(w: _Worker) -> None:
        if w.proc.poll() is None:
            try:
                assert w.proc.stdin is not None
                w.proc.stdin.close()
                w.proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                w.proc.kill()
                w.proc.wait()
        for stream in (w.proc.stdout,):
            if stream is not None:
                stream.close()
        w.stderr.close()

    @staticmethod
    def _stderr_tail(w: _Worker, lines: int = 6) -> str:
        w.stderr.flush()
        w.stderr.seek(0)
        text = w.stderr.read()
        tail = [ln for ln in text.splitlines() if ln.strip()][-lines:]
        return " | ".join(tail)

    def run(self, jobs: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
        """Run ``jobs`` (dicts with ``robot``, ``backend``, optional ``duration``/``options``/``behavior``)."""
        jobs = list(jobs)
        results: list[dict[str, Any] | None] = [None] * len(jobs)
        pending = deque(range(len(jobs)))
        while len(self._workers) < min(self.size, max(1, len(jobs))):
            self._workers.append(self._spawn())
        sel = selectors.DefaultSelector()
        try:
            while pending or any(w.job is not None for w in self._workers):
                for i, w in enumerate(self._workers):
                    if w.job is None and pending:
                        if w.proc.poll() is not None:
                            self._stop(w)
                            w = self._workers[i] = self._spawn()
                            self.restarts += 1
                        w.job = pending.popleft()
                        w.started = time.monotonic()
                        w.buffer = ""
                        assert w.proc.stdin is not None
                        try:
                            w.proc.stdin.write(json.dumps(dict(jobs[w.job])) + "\n")
                            w.proc.stdin.flush()
                        except OSError:
                            pass  # a dead worker: found below
                busy = [w for w in self._workers if w.job is not None]
                for w in busy:
                    assert w.proc.stdout is not None
                    try:
                        sel.register(w.proc.stdout, selectors.EVENT_READ, w)
                    except KeyError:
                        pass
                events = sel.select(timeout=0.5)
                for key, _ in events:
                    w = key.data
                    line = w.proc.stdout.readline() if w.proc.stdout is not None else ""
                    sel.unregister(key.fileobj)
                    if line:
                        assert w.job is not None
                        results[w.job] = json.loads(line)
                        w.job = None
                    else:  # EOF: the worker died
                        self._died(w, results, jobs)
                for w in self._workers:
                    if w.job is None:
                        continue
                    if w.proc.poll() is not None and not any(k.data is w for k, _ in events):
                        try:
                            sel.unregister(w.proc.stdout)  # type: ignore[arg-type]
                        except (KeyError, ValueError):
                            pass
                        self._died(w, results, jobs)
                    elif time.monotonic() - w.started > self.timeout:
                        try:
                            sel.unregister(w.proc.stdout)  # type: ignore[arg-type]
                        except (KeyError, ValueError):
                            pass
                        w.proc.kill()
                        w.proc.wait()
                        self._died(w, results, jobs, timed_out=True)
                for i, w in enumerate(self._workers):
                    if w.job is None and w.proc.poll() is not None:
                        self._stop(w)
                        self._workers[i] = self._spawn()
                        self.restarts += 1
                for key in list(sel.get_map().values()):
                    sel.unregister(key.fileobj)
        finally:
            sel.close()
        return [r if r is not None else {"ok": False, "error": "no result"} for r in results]

    def _died(
        self, w: _Worker, results: list[dict[str, Any] | None], jobs: list[Mapping[str, Any]], timed_out: bool = False
    ) -> None:
        assert w.job is not None
        rc = w.proc.wait()
        what = f"timed out after {self.timeout:g} s" if timed_out else f"process died (exit status {rc})"
        results[w.job] = {
            "ok": False,
            "loaded": False,
            "died": True,
            "error_type": "WorkerDied",
            "error": f"{what}: {self._stderr_tail(w)}",
            "returncode": rc,
        }
        w.job = None


def probe_in_subprocess(
    robot: str, backend: str, *, timeout: float = 120.0, duration: float = 0.02
) -> dict[str, Any]:
    """:func:`probe` in a fresh child process (see :class:`ProbePool`)."""
    with ProbePool(1, timeout=timeout) as pool:
        return pool.run([{"robot": str(robot), "backend": backend, "duration": duration}])[0]


if __name__ == "__main__":
    sys.exit(_worker_main())
