"""Block lockstep's backend half on MuJoCo: K control periods in one call, each reading kept, any tick restorable.

Issue 28 item 1. :class:`BlockStepper` runs ``write(k)`` (the caller writes tick ``k``'s setpoint
through :meth:`agentsdk.Backend.write`), the step and the read of K ticks back to back, as the
control loop would run them tick by tick but without the loop's per-tick phases in between: the
same MuJoCo calls in the same order, so every reading and every state is bit for bit what
tick-by-tick gives (``tests/test_block_stepper.py``). It keeps MuJoCo's integration state
(``mjSTATE_INTEGRATION``: the full physics, the controls, the applied forces and the solver's warm
start) before every ``every``-th tick of the block (a *checkpoint*; tick 0 always), and
:meth:`restore` puts MuJoCo back to where it stood before any tick (its checks found that tick to
be an event) from the latest checkpoint at or before it, replaying the ticks in between with the
caller's setpoints (the same calls: the same states). Saving the state before every tick cost
about as much as a reading per tick (1.5 µs, ``mj_getState``); events are rare, and replaying at
most ``every - 1`` ticks after one costs less than saving all the others.

A step that diverges (a warning counter moved, a non-finite acceleration) ends the block: the
exception the backend's own step raises at that tick is kept in :attr:`fault`, with the ticks
before it done and read, and MuJoCo's state left as the diverged step left it (exactly as a
tick-by-tick run leaves it when it raises). The backend's divergence checks cost about 2 µs per
step, so a block looks once, after its last step (MuJoCo counts every divergence and steps on),
and only a block that diverged runs again from its start with the checks after every step.

For a motion the caller need not write each setpoint through the backend: :meth:`BlockStepper.controls`
computes the controls the write would leave in ``ctrl`` for every tick of the block at once (the
servo law on all rows, the inverse-dynamics feed-forward per row with only its matrix products and
``mj_inverse``), and the block's ``write(k)`` puts row ``k`` into ``ctrl`` (tick 0 still writes its
setpoint: that sets the model arrays below).

When a block writes no more than those precomputed controls (a motion), or nothing after tick 0 (a
hold), its ticks after tick 0's write run as **one** ``mujoco.rollout`` call (:meth:`BlockStepper.run`
with ``stop``, the *open loop*): the same ``mj_step`` calls on the backend's own ``MjData`` with the
same inputs, no Python between them, so the same bits (``tests/test_block_stepper.py``). The rollout
is given every user input (``mjSTATE_USER``: it would reset applied forces, mocap and equality
switches it is not given), each reading's position and velocity come from the state it returns, and
its effort from the backend's per-joint effort sensors (the last sensors of the model, reading
exactly what :meth:`~agentsdk.Backend.read` returns); it clears MuJoCo's warning counters and stops
at a warning, so the counters are put back after it and a block that saw a warning runs again tick
by tick. Python's per-tick work in the stepper was ~1 µs per tick on arm3 (write, step call, three
reading copies); the rollout's per-step copies in C cost a fraction of that. An emergency stop or
latch from another thread that lands while the rollout runs (it releases the GIL, as ``mj_step``
does) is found after it: MuJoCo goes back to before tick 0 and no tick of the block is done, as if it
had landed just before the block. No rollout runs where its result could differ from tick by tick or
it would bypass something: a realtime backend (no effort sensors), a host effort map (mimic followers
or scattered dofs with MuJoCo's gravity compensation), the RK4 integrator (its last three stages skip
the sensors, so they keep the first stage's actuation while ``read()`` returns the last's), sensors
disabled in the model, a control or passive callback installed (it may change the inputs, which a
rollout sets again before every physics step), ``mujoco.mj_step`` replaced (a test's fault
injection), a MuJoCo without ``mujoco.rollout.Rollout`` (before 3.2.7), or once MuJoCo has counted
a warning (a rollout clears the counters, and MuJoCo logs a warning when its counter is 0: it would
log the warning again at every block); the block that meets the first warning logs it once.

Not restored: the model arrays :meth:`~agentsdk.Backend.write` sets when the gains or the
enabled joints change (the servo bias terms, the torque-off effort ranges); a block keeps them
constant (pre-planned motions write the loop's gains), which is the caller's precondition.
The control loop runs it through :mod:`agentsdk.block` (``MujocoBackend.block_stepper``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np
from mujoco import rollout as mujoco_rollout

from agentsdk.errors import InvalidValueError, SimulationDiverged

if TYPE_CHECKING:
    from agentsdk.backend import SetpointView

    from . import MujocoBackend

__all__ = ["BlockStepper"]

_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
#: a rollout's per-step inputs: the controls and every other user input (applied forces, mocap, equality
#: switches, userdata), which mujoco.rollout would otherwise reset to the model's defaults
_USER = mujoco.mjtState.mjSTATE_USER
#: a rollout's per-step output (and its start): the physics without the solver's warm start
_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
#: MuJoCo's step as imported: where it was replaced (a test's fault injection) no rollout runs, which would bypass it
_MJ_STEP = mujoco.mj_step
_NO_SENSORS = int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
#: the most physics steps one rollout runs (its buffers are sized for this many: a few MB on the humanoid)
OPEN_LOOP_STEPS = 2048
#: MuJoCo's rollout object (``mujoco.rollout.Rollout``, MuJoCo 3.2.7 and later), or None: no open loop
_ROLLOUT = getattr(mujoco_rollout, "Rollout", None)
#: callbacks MuJoCo calls inside a step that may change its inputs (ctrl, applied forces), which a
#: rollout sets again before every physics step and tick by tick writes once per tick or not at all
_INPUT_CALLBACKS = (mujoco.get_mjcb_control, mujoco.get_mjcb_passive)


class BlockStepper:
    """Steps ``backend`` up to ``capacity`` control periods per call (:meth:`run`); :meth:`restore` rolls back."""

    def __init__(self, backend: MujocoBackend, capacity: int, every: int = 16) -> None:
        if capacity < 1:
            raise InvalidValueError(f"capacity must be at least 1, got {capacity}")
        if every < 1:
            raise InvalidValueError(f"every must be at least 1 tick, got {every}")
        self._b = backend
        m = backend.model
        self.capacity = capacity
        #: a checkpoint before every ``every``-th tick (0, every, 2 every, ...)
        self.every = every
        #: ``states[i]``: MuJoCo's integration state before tick ``i * every`` of the last block
        self.states = np.empty(((capacity - 1) // every + 1, mujoco.mj_stateSize(m, _STATE)))
        #: ticks the last :meth:`run` completed, and the divergence that ended it (None: it did not)
        self.done = 0
        self.fault: SimulationDiverged | None = None
        #: MuJoCo stands where the last run left it (no restore since)
        self._at_end = True
        #: the controls :meth:`~agentsdk.Backend.write` computes depend on the setpoint alone (no host
        #: ``g(q)`` of the measured position) and ``mj_step`` leaves ``ctrl`` as written (it clamps a
        #: copy; a rejected control zeroes it, but that step diverges and ends the block): a setpoint
        #: that stays the same over a block (a hold) needs its write at the first tick only
        self.write_once = backend.gravity_route != "host"
        self._warned: tuple[np.ndarray, bytes] = (np.zeros(0), b"")
        #: :meth:`controls`' rows (one per tick) and its work array
        self._ctrls = np.empty((capacity, m.nu))
        self._ctrl_tmp = np.empty((capacity, len(backend.joints)))
        self._ctrl_ff = np.empty((capacity, len(backend.joints)))
        from agentsdk.backend import Backend

        from . import MujocoBackend

        #: the step and write a block reproduces: the backend's own (see :meth:`ready`)
        self._stock = (Backend.step, MujocoBackend._step, Backend.write, MujocoBackend._write)
        #: checkpoints of the last run are ``every`` ticks apart (an open-loop run keeps tick 0's only)
        self._every_run = every
        #: a run's ticks may be one mujoco.rollout (see :meth:`run`): each step's effort is a plain
        #: gather of one of the backend's effort sensors, which hold what read() returns after the step
        #: (not with RK4, whose last stages skip the sensors: they keep the first stage's actuation)
        n = len(backend.joints)
        self._ticks_open = min(capacity, OPEN_LOOP_STEPS // backend._nsub)
        self._open_loop = (_ROLLOUT is not None and backend._effort_sensors and backend._effort_map is None
                           and m.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4 and self._ticks_open >= 2)
        self._roller: Any = None  # mujoco's rollout object, made at the first open-loop run
        #: the warnings MuJoCo only counts (no divergence: the backend's own checks ignore them), and
        #: those of them the last rollout counted (see :meth:`run`: the replay does not log them again)
        self._counted_only = np.ones(len(backend.data.warning.number), dtype=bool)
        self._counted_only[np.asarray(backend._warn_codes, dtype=np.intp)] = False
        self._rollout_counted = np.zeros_like(self._counted_only)
        # the rollout's arrays (made with it): inputs per step, outputs per step, the start
        self._ro: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        off_q = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_TIME)
        off_v = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_TIME | mujoco.mjtState.mjSTATE_QPOS)
        a = backend._effort_sensor_adr
        #: where a reading's position, velocity and effort are in a rollout's state and sensor rows
        self._cols = (_columns(backend._qadr + off_q), _columns(backend._dadr + off_v), slice(a, a + n))

    def controls(self, rows: np.ndarray, setpoint: SetpointView) -> Callable[[int], None] | None:
        """The controls :meth:`~agentsdk.Backend.write` computes from each of K setpoints, all before the block.

        ``rows`` (K, 7, n): each tick's setpoint rows (:attr:`agentsdk.loop.Setpoint.FIELDS` order);
        ``setpoint``: the live view, whose ``mode`` and ``enabled`` rows are the block's (constant).
        Returns ``put(j)``, which writes tick ``j``'s controls into MuJoCo's ``ctrl`` (bit for bit
        what the backend's write of that setpoint leaves there: the servo law's element operations
        in the same order, on all K rows at once, and the inverse-dynamics feed-forward of each
        moving reference as the write computes it), or None where the controls depend on more than
        the setpoint (the host's ``g(q)`` of the measured position) or a joint's torque is off.
        The block's first tick still runs the whole write (it sets the model arrays that the gains
        and the enabled joints decide, constant over a block); ``put`` serves the others.
        """
        b = self._b
        K = len(rows)
        if b._gravity is not None or K > self.capacity or setpoint.enabled.tobytes() != b._all_enabled:
            return None
        ctrls = self._ctrls[:K]
        tmp = self._ctrl_tmp[:K]
        # ctrl = kp q_des + kd v_des + effort_ff (+ the feed-forward), as MujocoBackend._write per tick
        np.multiply(rows[:, 3], rows[:, 0], out=ctrls)
        np.multiply(rows[:, 4], rows[:, 1], out=tmp)
        ctrls += tmp
        ctrls += rows[:, 2]
        inverse = b._inverse
        if inverse is not None:
            # InverseDynamicsTerm.moving per row: a dot product of squares is 0 exactly when every rounded
            # square is (no term is negative), whatever the order of its sum
            sq = np.multiply(rows[:, 1], rows[:, 1], out=tmp)
            moving = np.not_equal(sq, 0.0).any(axis=1)
            np.multiply(rows[:, 6], rows[:, 6], out=tmp)
            moving |= np.not_equal(tmp, 0.0).any(axis=1)
            qadr, followers = b._qadr, b._qdes_followers

            def put_q(qpos: np.ndarray, q: np.ndarray) -> None:  # the desired positions, as the write puts each
                qpos[:, qadr] = q
                for adr, leader, c1, c0 in followers:
                    qpos[:, adr] = c0 + c1 * q[:, leader]

            idx = np.flatnonzero(moving)
            if len(idx):
                ff = inverse.compute_block(b._qdes, put_q, rows[:, 0], rows[:, 1], rows[:, 6], idx,
                                           self._ctrl_ff[:K], setpoint.mode)
                ctrls[idx] += ff[idx]
        return _Put(b._ctrl, ctrls)

    def ready(self) -> bool:
        """The backend's ``step``/``_step``/``write``/``_write`` are MuJoCo's own: a block makes those calls itself.

        A subclass or an instance (a test's fault injection) that replaces them would be bypassed by
        a block (a motion block writes its precomputed controls, :meth:`controls`): then no block runs,
        every tick goes through the backend's step and write as without blocks.
        """
        b = self._b
        cls = type(b)
        own = getattr(b, "__dict__", None) or {}
        return ((cls.step, cls._step, cls.write, cls._write) == self._stock
                and "step" not in own and "_step" not in own and "write" not in own and "_write" not in own)

    def run(self, write: Callable[[int], bool | None], count: int, readings: np.ndarray,
            stop: Callable[[], bool] | None = None, controls: Callable[[int], None] | None = None) -> int:
        """Run ticks ``0 .. count - 1``: ``write(k)``, step one control period, read into ``readings[k]`` (3, n).

        Returns the ticks done: ``count``, or fewer when a step diverged (:attr:`fault`) or
        ``write(k)`` returned False (it wrote nothing: the block ends before tick ``k``).

        *Open loop*: ``stop`` given says that after tick 0 the ticks write nothing but ``controls(k)``
        (the ``put`` of this stepper's :meth:`controls` for this block), or with ``controls`` None
        nothing at all (a hold, :attr:`write_once`), and that ``write(k)`` returns False exactly when
        ``stop()`` is true. Then, after tick 0's write, all the ticks are one ``mujoco.rollout``
        call, the same ``mj_step`` calls with the same inputs (no Python between the steps): each
        reading comes from the state it returns and the backend's effort sensors. ``stop()`` is
        asked after it: true (an emergency stop or latch from another thread landed during the
        block), and MuJoCo goes back to before tick 0 and no tick is done, as when it lands before
        tick 0's write. Only tick 0's checkpoint is kept (:meth:`restore` replays from it), and a
        warning during the rollout runs the block again tick by tick (warnings and divergences
        as the backend's own step reports them; MuJoCo logs the warning once). A rollout clears
        MuJoCo's warning counters (MuJoCo logs a warning when its counter is 0), so once MuJoCo
        has counted a warning, blocks run tick by tick.
        """
        if not 0 <= count <= self.capacity:
            raise InvalidValueError(f"count must be within 0..{self.capacity}, got {count}")
        b = self._b
        self.fault = None
        self.done = 0
        self._at_end = True
        self._every_run = self.every
        # the backend's record of MuJoCo's warning counters before the block (see restore)
        self._warned = (b._warn.copy(), b._warn_bytes)
        w = b.data.warning
        counters = (w.number.copy(), w.lastinfo.copy())  # MuJoCo's own, all of them
        # (no rollout once MuJoCo has counted a warning: a rollout clears the counters, so MuJoCo would
        # log a warning it logged before again, at every block that meets it)
        quiet: np.ndarray | None = None
        if (stop is not None and self._open_loop and 2 <= count <= self._ticks_open
                and (controls is None or (isinstance(controls, _Put) and controls.ctrl is b._ctrl
                                          and count <= len(controls.ctrls)))
                and mujoco.mj_step is _MJ_STEP and not b.model.opt.disableflags & _NO_SENSORS
                and not any(get() is not None for get in _INPUT_CALLBACKS) and not counters[0].any()):
            done = self._run_open_loop(write, count, readings, stop, controls, counters)
            if done is not None:
                self.done = done
                return done
            self._every_run = self.every  # again tick by tick, from the block's start
            # The rollout met a warning and MuJoCo logged it (its first, as the counters were all 0). So
            # that the ticks again do not log it a second time, the warnings it counted that only count
            # start at 1 (MuJoCo logs at 0 only) and are 1 less at the end: the counts of tick by tick.
            # (A divergence is logged again: the backend's checks look at those counters, and it faults.)
            quiet = self._rollout_counted
            if quiet.any():
                counters = (counters[0] + quiet, counters[1])
                b.data.warning.number[quiet] = 1
            else:
                quiet = None
        try:
            done = self._run(write, count, readings)
            if done and self._diverged():
                # a step diverged: again from the block's start (MuJoCo's warning counters too) with the
                # backend's checks after every step, which end the block at that tick (rare: a diverged
                # simulation faults the loop)
                self._restart(counters)
                done = self._run_checked(write, count, readings)
        finally:
            if quiet is not None:
                b.data.warning.number[quiet] -= 1
        self.done = done
        return done

    def _run(self, write: Callable[[int], bool | None], count: int, readings: np.ndarray) -> int:
        """The ticks without the backend's per-step divergence checks (:meth:`_diverged` looks once, after them).

        A divergence moves a warning counter (MuJoCo counts it, resets the state and steps on), and a
        non-finite acceleration after one step is a warning of the next (``mj_checkVel``): so a block
        that ends with the counters as they were and a finite acceleration had no divergence.
        """
        b = self._b
        m, d = b.model, b.data
        nsub = b._nsub
        states, every = self.states, self.every
        get_state, step = mujoco.mj_getState, mujoco.mj_step
        read = b.read
        # joints consecutive in qpos / qvel, effort read as it is: read() returns the same views every tick
        fresh = b._gather or b._effort_map is not None
        q, v, e = read()
        qs, vs, es = readings[:, 0], readings[:, 1], readings[:, 2]  # (one view per row kind, not per tick)
        for k in range(count):
            if not k % every:  # before the write: the state tick by tick stands in before tick k
                get_state(m, d, states[k // every], _STATE)
            if write(k) is False:
                return k  # (restore(k) is then the state as it stands)
            step(m, d, nsub)
            if fresh:
                q, v, e = read()
            qs[k] = q
            vs[k] = v
            es[k] = e
        return count

    def _run_open_loop(self, write: Callable[[int], bool | None], count: int, readings: np.ndarray,
                       stop: Callable[[], bool], controls: Callable[[int], None] | None,
                       counters: tuple[np.ndarray, np.ndarray]) -> int | None:
        """:meth:`run`'s open loop: tick 0's write, then every step as one rollout; None: run it tick by tick.

        None when the rollout saw a warning (it stops stepping at one) or the acceleration is not
        finite: MuJoCo is then back before tick 0 and the caller runs the block tick by tick.
        """
        b = self._b
        m, d = b.model, b.data
        nsub = b._nsub
        start = self.states[0]
        mujoco.mj_getState(m, d, start, _STATE)
        self._every_run = self.capacity + 1  # only tick 0's checkpoint (restore: c = 0 for every k)
        if write(0) is False:
            return 0
        if self._ro is None:
            assert _ROLLOUT is not None  # (else no open loop)
            self._roller = _ROLLOUT(nthread=0)  # on this thread (it releases the GIL, as mj_step)
            steps = self._ticks_open * nsub
            self._ro = (np.empty((1, steps, mujoco.mj_stateSize(m, _USER))),
                        np.empty((1, steps, mujoco.mj_stateSize(m, _FULL))),
                        np.empty((1, steps, m.nsensordata)),
                        np.empty((1, mujoco.mj_stateSize(m, _FULL))),
                        np.empty((1, m.nv)))
        inputs, out, sensed, s0, w0 = self._ro
        N = count * nsub
        steps_in = inputs[:, :N]
        rows = steps_in[0]
        mujoco.mj_getState(m, d, rows[0], _USER)  # the inputs as tick 0's write left them, for every step
        rows[1:] = rows[0]
        if isinstance(controls, _Put):
            # tick k's controls for each of its physics steps (ctrl is first in mjSTATE_USER)
            rows.reshape(count, nsub, -1)[1:, :, : m.nu] = controls.ctrls[1:count, None, :]
        mujoco.mj_getState(m, d, s0[0], _FULL)
        w0[0] = d.qacc_warmstart
        w = d.warning
        # (skip_checks: the arrays are made for this model, C-contiguous float64, and the outputs are
        # written in place, as their size is exactly N steps)
        self._roller.rollout([m], [d], s0, steps_in, control_spec=int(_USER), skip_checks=True, nstep=N,
                             initial_warmstart=w0, state=out[:, :N], sensordata=sensed[:, :N])
        warned = w.number.any()  # (the rollout clears the counters first and stops at any warning)
        np.logical_and(w.number, self._counted_only, out=self._rollout_counted)
        w.number[:], w.lastinfo[:] = counters
        if warned or self._diverged():
            self._restart(counters)
            return None
        if stop():
            # an emergency stop or latch landed during the block: as if before tick 0's write (the
            # torque-off model arrays it set stay; the loop's next tick enforces it)
            self._restart(counters)
            return 0
        qc, vc, ec = self._cols
        st = out[0, nsub - 1 : N : nsub]
        readings[:count, 0] = st[:, qc]
        readings[:count, 1] = st[:, vc]
        readings[:count, 2] = sensed[0, nsub - 1 : N : nsub, ec]
        return count

    def _restart(self, counters: tuple[np.ndarray, np.ndarray]) -> None:
        """MuJoCo back to before the block's tick 0, its warning counters too."""
        b = self._b
        mujoco.mj_setState(b.model, b.data, self.states[0], _STATE)
        w = b.data.warning
        w.number[:], w.lastinfo[:] = counters
        b._warn[...] = self._warned[0]
        b._warn_bytes = self._warned[1]

    def _diverged(self) -> bool:
        """A step of the block diverged: the warning counters moved, or the acceleration is not finite."""
        b = self._b
        if b._warnings().tobytes() != b._warn_bytes:
            return True
        qacc, acc2 = b._qacc, b._acc2
        np.dot(qacc, qacc, out=acc2)
        return not math.isfinite(acc2.item()) and not np.isfinite(qacc).all()

    def _run_checked(self, write: Callable[[int], bool | None], count: int, readings: np.ndarray) -> int:
        """The ticks with the backend's checks after every step: a divergence ends the block there (:attr:`fault`)."""
        b = self._b
        m, d = b.model, b.data
        nsub = b._nsub
        states, every = self.states, self.every
        get_state, step = mujoco.mj_getState, mujoco.mj_step
        qacc, acc2 = b._qacc, b._acc2
        read = b.read
        for k in range(count):
            if not k % every:
                get_state(m, d, states[k // every], _STATE)
            if write(k) is False:
                return k
            t0 = d.time
            step(m, d, nstep=nsub)
            # the backend's own per-step checks (MujocoBackend._step), in the same order
            view = b._warn_view
            try:
                if view is None or view.tobytes() != b._warn_bytes:
                    b._check_warnings(t0)
                np.dot(qacc, qacc, out=acc2)
                if not math.isfinite(acc2.item()) and not np.isfinite(qacc).all():
                    raise SimulationDiverged(f"MuJoCo state became non-finite at t={d.time:.4f} s")
            except SimulationDiverged as exc:
                self.fault = exc
                return k
            q, v, e = read()
            row = readings[k]
            row[0] = q
            row[1] = v
            row[2] = e
        return count

    def restore(self, k: int, write: Callable[[int], object]) -> None:
        """Put MuJoCo back to where it was before tick ``k`` of the last block (``k == done``: its end).

        From the latest checkpoint at or before ``k``, ticks ``c .. k - 1`` run again: ``write(j)``
        writes tick ``j``'s setpoint as the block did (whatever the torque state is now: an
        emergency stop that landed during the block came after them; the loop's next tick enforces
        it), then the step. After a divergence the backend forgets it too: stepping tick ``done``
        again diverges again, with the backend's own error (as tick by tick).
        """
        if not 0 <= k <= self.done:
            raise InvalidValueError(f"tick {k} is not within the last block (0..{self.done})")
        if k == self.done and self.fault is None and self._at_end:
            return  # the state as it stands
        self._at_end = False
        b = self._b
        m, d = b.model, b.data
        every = self._every_run
        c = k - k % every
        mujoco.mj_setState(m, d, self.states[c // every], _STATE)
        step, nsub = mujoco.mj_step, b._nsub
        for j in range(c, k):
            write(j)
            step(m, d, nstep=nsub)
        if self.fault is not None:
            b._warn[...] = self._warned[0]
            b._warn_bytes = self._warned[1]


class _Put:
    """:meth:`BlockStepper.controls`' result: ``put(j)`` writes tick ``j``'s controls; ``ctrls`` holds them all."""

    __slots__ = ("ctrl", "ctrls")

    def __init__(self, ctrl: np.ndarray, ctrls: np.ndarray) -> None:
        self.ctrl, self.ctrls = ctrl, ctrls

    def __call__(self, j: int) -> None:
        self.ctrl[...] = self.ctrls[j]


def _columns(idx: np.ndarray) -> slice | np.ndarray:
    """``idx`` as a slice where it is consecutive (a view, no gather), else the index array."""
    if len(idx) and (np.diff(idx) == 1).all():
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx
