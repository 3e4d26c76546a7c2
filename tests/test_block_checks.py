"""Block lockstep, the checks over K stacked states (issue 28 item 1): the same decisions as per tick.

Each built-in check's block form (:class:`agentsdk.checks.BlockCheck`, the sensor gate's
``block_quiet``) says how many leading ticks of a block pass quietly; a differential test runs
random blocks (random limits, windows, continuous joints, watched masks; limit hits, error
spikes, NaN readings, jumps and late readings injected at random ticks) through two copies of the
check: one tick by tick, one as ``block_quiet`` + ``commit_block`` + tick by tick from the
tick it stopped at. Every result, every state array and the stop tick itself must agree exactly:
the block stops at the first tick whose per-tick call does anything but pass quietly.
"""

from __future__ import annotations

import copy
import functools
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from agentsdk.backend import ModeCode
from agentsdk.checks import BlockCheck, MeasuredPositionCheck
from agentsdk.following import FollowingErrorCheck
from agentsdk.loop import Setpoint, StateBuffer
from agentsdk.plausibility import SensorGate
from agentsdk.types import JointInfo

CASES = 400  # per check: 1,200 random blocks in all


def _joints(rng: np.random.Generator, n: int) -> tuple[JointInfo, ...]:
    out = []
    for i in range(n):
        kind = rng.choice(["revolute", "revolute", "prismatic", "continuous"])
        lo = float(rng.uniform(-3.0, 0.0))
        hi = float(rng.uniform(0.1, 3.0))
        if kind == "continuous":
            lo, hi = -np.inf, np.inf
        out.append(JointInfo(f"j{i}", kind, lo, hi, max_velocity=float(rng.uniform(0.5, 5.0)), max_effort=50.0))
    return tuple(out)


def _ticks(rng: np.random.Generator, K: int, period: float) -> np.ndarray:
    tick0 = int(rng.integers(1, 100_000))
    return (tick0 + np.arange(K)) * period


def _view(states: np.ndarray, k: int) -> Any:
    buf = StateBuffer(states.shape[2])
    buf.block[...] = states[k]
    return buf.view


def _inject(rng: np.random.Generator, q: np.ndarray, scale: float) -> None:
    """Rare spikes, NaN and inf at random ticks and joints."""
    K, n = q.shape
    for _ in range(int(rng.integers(0, 3))):
        k, j = int(rng.integers(0, K)), int(rng.integers(0, n))
        q[k, j] = rng.choice([np.nan, np.inf, -np.inf, q[k, j] + scale * rng.choice([-1.0, 1.0]) * rng.uniform(1, 4)])


def _differential(check_a: BlockCheck, check_b: BlockCheck, ts: np.ndarray, states: np.ndarray, sps: np.ndarray,
                  set_sp: Any, changed: Any, busy: Any, kept: Any = None) -> int:
    """Run both copies; returns the stop tick.

    A tick is an event when ``busy(check)`` holds before it (a state a block does not start from:
    the check arms joints, a persistence timer runs) or when it returns a violation or changes
    ``changed(check)``. ``kept(check)``, if given, is what the commit must leave: as before the stop tick.
    """
    K = len(ts)
    results_a = []
    first_event = K
    kept_a = []
    for k in range(K):
        if kept is not None:
            kept_a.append(kept(check_a))
        set_sp(check_a, sps[k])
        before = changed(check_a)
        was_busy = busy(check_a)
        r = check_a(float(ts[k]), _view(states, k))
        results_a.append(r)
        if first_event == K and (was_busy or r is not None or changed(check_a) != before):
            first_event = k
    k = check_b.block_quiet(ts, states, sps)
    assert k == first_event
    check_b.commit_block(ts, states, sps, k)
    if kept is not None:
        assert kept(check_b) == (kept_a[k] if k < K else kept(check_a))
    results_b = [None] * k
    for j in range(k, K):
        set_sp(check_b, sps[j])
        results_b.append(check_b(float(ts[j]), _view(states, j)))
    assert results_a == results_b
    return k


@pytest.mark.parametrize("seed", range(4))
def test_the_measured_position_check_decides_a_block_as_tick_by_tick(seed: int) -> None:
    rng = np.random.default_rng(seed)
    stops = 0
    for _ in range(CASES // 4):
        n = int(rng.integers(1, 12))
        joints = _joints(rng, n)
        tol = float(rng.choice([0.0, 0.05, 0.2]))
        # two checks built alike (a deep copy would cut the row views the check compares through)
        a, b = MeasuredPositionCheck(joints, tol, 1), MeasuredPositionCheck(joints, tol, 1)
        lo = np.array([j.lower if np.isfinite(j.lower) else -5.0 for j in joints])
        hi = np.array([j.upper if np.isfinite(j.upper) else 5.0 for j in joints])
        K = int(rng.integers(1, 300))
        q = lo + (hi - lo) * rng.uniform(0.0, 1.0, size=(K, n))
        _inject(rng, q, 1.0)
        if rng.random() < 0.4:  # a joint that reaches or leaves its limits (+ tolerance), at either end
            j, k0 = int(rng.integers(0, n)), int(rng.integers(0, K))
            over = float(rng.choice([0.0, 1e-9, 1e-4, 0.01]))
            q[k0:, j] = hi[j] + tol + over if rng.random() < 0.5 else lo[j] - tol - over
        states = np.zeros((K, 3, n))
        states[:, 0, :] = q
        if rng.random() < 0.9:  # armed by a first reading inside (else: a block waits for the arming)
            for c in (a, b):
                c(0.0, _view(np.array([[(lo + hi) / 2, np.zeros(n), np.zeros(n)]]), 0))
        k = _differential(a, b, _ticks(rng, K, 0.002), states, np.zeros((K, n)), lambda c, sp: None,
                          lambda c: c._armed.tobytes(), lambda c: not c._all_armed)
        stops += k < K
    assert stops > 10  # limit hits were seen, not only quiet blocks


def _following(rng: np.random.Generator, n: int) -> tuple[FollowingErrorCheck, Setpoint, FollowingErrorCheck, Setpoint]:
    """Two following-error checks built alike, each reading its own setpoint."""
    joints = _joints(rng, n)
    kp = rng.choice([0.0, 50.0, 200.0], size=n, p=[0.15, 0.4, 0.45])
    mode = rng.choice([int(ModeCode.POSITION), int(ModeCode.VELOCITY)], size=n, p=[0.85, 0.15])
    enabled = rng.random(n) < 0.9
    windows = rng.uniform(0.05, 0.5, size=n)
    persist = float(rng.choice([0.0, 0.005, 0.1]))
    out: list[Any] = []
    for _ in range(2):
        sp = Setpoint(n)
        sp.kp[:], sp.mode[:], sp.enabled[:] = kp, mode, enabled
        loop = SimpleNamespace(joints=joints, period=0.002, setpoint=sp.view, controller_desired=np.full(n, np.nan))
        out += [FollowingErrorCheck(loop, windows, persist, 2), sp]  # type: ignore[arg-type]
    return out[0], out[1], out[2], out[3]


@pytest.mark.parametrize("seed", range(4))
def test_the_following_error_check_decides_a_block_as_tick_by_tick(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    stops = 0
    for _ in range(CASES // 4):
        n = int(rng.integers(1, 12))
        a, sp_a, b, sp_b = _following(rng, n)
        K = int(rng.integers(1, 300))
        ts = _ticks(rng, K, 0.002)
        sps = rng.uniform(-4.0, 4.0, size=(K, n))
        q = sps + rng.normal(0.0, 0.05, size=(K, n)) * rng.uniform(0.1, 4.0)
        q[:, a._continuous] += 2 * np.pi * rng.integers(-2, 3, size=(K, int(a._continuous.sum())))
        _inject(rng, q, 0.6)
        states = np.zeros((K, 3, n))
        states[:, 0, :] = q
        if rng.random() < 0.3:  # a check that ran before: a tick with an error outside (tracking), or inside
            st = np.zeros((1, 3, n))
            st[0, 0, :] = rng.choice([0.0, 1.0]) * a.windows * 1.5
            for c in (a, b):
                c(float(ts[0] - 0.002), _view(st, 0))
        sps_of = {id(a): sp_a, id(b): sp_b}

        def set_sp(c: Any, row: np.ndarray, sps_of: dict[int, Setpoint] = sps_of) -> None:
            sps_of[id(c)].position[:] = row

        with np.errstate(invalid="ignore"):  # inf on a continuous joint: the per-tick wrap warns too
            k = _differential(a, b, ts, states, sps, set_sp, lambda c: (c._tracking, c._since.tobytes()),
                              lambda c: c._tracking, lambda c: (c.peak.tobytes(), c._last_t))
        stops += k < K
        assert a.peak.tobytes() == b.peak.tobytes()
        assert a._since.tobytes() == b._since.tobytes()
        assert (a._tracking, a._last_t) == (b._tracking, b._last_t)
    assert stops > 10


def _gate(rng: np.random.Generator, n: int) -> tuple[SensorGate, StateBuffer]:
    joints = _joints(rng, n)
    buf = StateBuffer(n)
    gate = SensorGate(joints, buf.position, buf.velocity, buf.effort, margin=1.5, floor=0.01,
                      tolerance=float(rng.choice([0.05, 0.2])), period=0.002)
    return gate, buf


def _counted(calls: list[int], full: Any, k: int, *args: Any) -> None:
    calls.append(k)
    full(*args)


def _gate_state(g: SensorGate) -> tuple[Any, ...]:
    return (g._position.tobytes(), g._velocity.tobytes(), g._effort.tobytes(), g._t_read, g._uniform,
            g._dt, g.suspect.tobytes(), g.rejected.tobytes(), g._t_bad.tobytes(), g._t_ok.tobytes(),
            [(r.index, r.quantity, r.reason) for r in g._new])


@pytest.mark.parametrize("seed", range(4))
def test_the_sensor_gate_decides_a_block_as_tick_by_tick(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    stops = 0
    for _ in range(CASES // 4):
        n = int(rng.integers(1, 12))
        gate_a, _ = _gate(rng, n)
        K = int(rng.integers(1, 300))
        period = 0.002
        ts = _ticks(rng, K + 2, period)
        lo = np.array([-2.0] * n)
        q0 = rng.uniform(-0.5, 0.5, size=n)
        gate_a.baseline(q0, np.zeros(n), np.zeros(n), float(ts[0]))
        if rng.random() < 0.9:  # a first fast-path reading caches the reach
            gate_a.accept(q0, np.zeros(n), np.zeros(n), float(ts[1]))
        ts = ts[2:]
        if rng.random() < 0.1:  # a late reading: a stalled loop
            ts[int(rng.integers(0, K)):] += 0.01
        if rng.random() < 0.1:  # an early reading: a shorter time step than the cached reach's
            ts[int(rng.integers(0, K)):] -= 0.001
        vmax = gate_a._vmax
        steps = rng.uniform(-1.0, 1.0, size=(K, n)) * vmax * period * rng.uniform(0.1, 2.5)
        q = q0 + np.cumsum(steps, axis=0) + lo * 0
        v = rng.normal(size=(K, n))
        e = rng.normal(size=(K, n))
        _inject(rng, q, 0.5)
        _inject(rng, v, 1.0)
        _inject(rng, e, 1.0)
        states = np.stack([q, v, e], axis=1)
        gate_b = copy.deepcopy(gate_a)
        # per tick
        first_event = K
        full_calls: list[int] = []
        orig_full = gate_a._full
        for k in range(K):
            dt_before = gate_a._dt
            calls = len(full_calls)
            gate_a._full = functools.partial(_counted, full_calls, orig_full, k)  # type: ignore[method-assign]
            gate_a.accept(q[k], v[k], e[k], float(ts[k]))
            if first_event == K and (len(full_calls) > calls or gate_a._dt != dt_before):
                first_event = k
        del gate_a._full
        k = gate_b.block_quiet(ts, states)
        assert k == first_event
        gate_b.commit_block(ts, states, k)
        for j in range(k, K):
            gate_b.accept(q[j], v[j], e[j], float(ts[j]))
        assert _gate_state(gate_a) == _gate_state(gate_b)
        stops += k < K
    assert stops > 10


@pytest.mark.parametrize("step", ["auto", None])
async def test_the_limit_filter_decides_a_block_as_tick_by_tick(step: Any) -> None:
    """The LIMIT tick's common path over K setpoints at once (``CommandFilter.block_quiet``): random
    references near and past the bounds, velocity and effort limits and the step window, NaN."""
    import agentsdk
    from agentsdk.loop import Setpoint

    async with agentsdk.connect("mock", robot="arm3", safety={"max_position_step": step}) as robot:
        f = robot.safety._filter
        lim = f.limiter
        loop = robot._loop
        n = len(robot.joints)
        rng = np.random.default_rng(7)
        lo, hi = np.where(np.isfinite(lim.lo), lim.lo, -3.0), np.where(np.isfinite(lim.hi), lim.hi, 3.0)
        stops = quiet = 0
        for _ in range(CASES):
            K = int(rng.integers(1, 200))
            w = (lim.step if lim.step is not None else np.full(n, 0.01)) * rng.uniform(0.2, 1.3)
            q = np.clip(rng.uniform(lo, hi) + np.cumsum(rng.uniform(-1, 1, size=(K, n)) * w, axis=0), lo - 0.01, hi)
            rows = np.zeros((K, 3, n))
            rows[:, 0] = q
            rows[:, 1] = rng.uniform(-1, 1, size=(K, n)) * lim.vmax * rng.uniform(0.5, 1.05)
            rows[:, 2] = rng.uniform(-1, 1, size=(K, n)) * lim.emax * rng.uniform(0.5, 1.05)
            if rng.random() < 0.3:
                rows[int(rng.integers(0, K)), int(rng.integers(0, 3)), int(rng.integers(0, n))] = np.nan
            written0 = q[0] if rng.random() < 0.8 else q[0] + w * rng.uniform(-2, 2)
            # tick by tick
            f._written[...] = written0
            sp = Setpoint(n)
            sp.mode[:], sp.enabled[:] = loop.setpoint.mode, loop.setpoint.enabled
            after, first_event = [], K
            for k in range(K):
                sp.block[0:3] = rows[k]
                f.tick(float(k), loop.state, sp)
                after.append(sp.block[0:3].copy())
                if first_event == K and sp.block[0:3].tobytes() != rows[k].tobytes():
                    first_event = k  # the tick changed the setpoint: not quiet
            written_a = f._written.copy()
            # as a block, then tick by tick from where it stopped
            f._written[...] = written0
            k = f.block_quiet(rows, sp.mode, sp.enabled)
            assert k == first_event
            f.commit_block(rows, k)
            for j in range(k, K):
                sp.block[0:3] = rows[j]
                f.tick(float(j), loop.state, sp)
                assert sp.block[0:3].tobytes() == after[j].tobytes()
            assert f._written.tobytes() == written_a.tobytes()
            stops += k < K
            quiet += k
        assert stops > 10 and quiet > 20 * CASES  # both outcomes, many quiet ticks
        assert f.block_quiet(rows[:0], sp.mode, sp.enabled) == 0
