"""Block lockstep's backend half on PyBullet: K control periods back to back, each reading kept, any tick restorable.

Issue 28 item 4. What :mod:`backends.mujoco.block` is for MuJoCo: :class:`BlockStepper` runs
``write(k)`` (the caller writes tick ``k``'s setpoint through :meth:`agentsdk.Backend.write`), the
backend's own substeps (:meth:`PybulletBackend.substeps`: the servo law, its implicit-damping solve,
``stepSimulation``, the divergence check) and the read of K ticks without the control loop's
per-tick phases in between, so every reading and every state is bit for bit what tick-by-tick
gives; :mod:`agentsdk.block` judges the K states and commits the quiet ones. The write runs every
tick (the gravity term ``g(q)`` is the measured position's), as the raw loop's; the block saves
the loop's work around it.

Rolling back (:meth:`BlockStepper.restore`) without ``saveState``: PyBullet's ``saveState``
serializes the whole world (0.8 ms on arm3, 2 ms on the humanoid per call), far more than a tick.
The state of a fixed-base multibody is its joint positions and velocities, which the backend reads
after every substep anyway: each tick's start state is kept (the last substep's ``q``, ``v`` of
every dof, the servo torque and the backend's time) and ``resetJointStatesMultiDof`` puts it
back, bit for bit (``tests/test_block_stepper_pybullet.py``). What that leaves out is PyBullet's
contact cache: a persistent contact point carries its solver impulse into the next step (warm
start), and neither a joint reset nor ``restoreState`` removes it. So a block starts only while the
world holds no contact point and ends after the first tick that leaves one (``getContactPoints``,
~1 µs per tick): every tick a rollback can go back to started without one, as tick by tick. The
points a restore may leave in the cache are that last tick's new ones, found within the contact
threshold (2 cm) of a step that started with none: the solver's impulse on such a speculative
point is exactly 0 (it would take an approach of 20 m/s within one 1 ms substep to close the
gap), so it warm-starts nothing, and on the ticks replayed after the restore it is farther away
(dropped by the next collision pass) or again an inactive row whose impulse stays 0. That is an
argument about Bullet's solver, checked (the humanoid swinging its limbs into each other, every
rollback continuing bit for bit through the contact), not a guarantee the API gives.

Not blocked (``ready()`` False, every tick on its own): a floating base (its implicit step keeps
the last substeps' contact forces: :mod:`.floating`), mimic joints (gear constraints), a backend
whose ``write``/``step``/``substeps`` are replaced (a subclass or a test's fault injection).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pybullet as p

from agentsdk.errors import InvalidValueError, SimulationDiverged

if TYPE_CHECKING:
    from . import PybulletBackend

__all__ = ["BlockStepper"]


class BlockStepper:
    """Steps ``backend`` up to ``capacity`` control periods per call (:meth:`run`); :meth:`restore` rolls back."""

    def __init__(self, backend: PybulletBackend, capacity: int) -> None:
        if capacity < 1:
            raise InvalidValueError(f"capacity must be at least 1, got {capacity}")
        self._b = backend
        self.capacity = capacity
        nd = len(backend._dofs)
        #: the start state of tick k of the last run: every dof's q and v, the servo torque, the time
        self._q = np.empty((capacity + 1, nd))
        self._v = np.empty((capacity + 1, nd))
        self._tau = np.empty((capacity + 1, len(backend.joints)))
        self._time = np.empty(capacity + 1)
        #: ticks the last :meth:`run` completed, and the divergence that ended it (None: it did not)
        self.done = 0
        self.fault: SimulationDiverged | None = None
        #: PyBullet stands where the last run left it (no restore since)
        self._at_end = True
        #: the last run's readings where they hold each tick's end state (every dof commanded, in order)
        self._readings: np.ndarray | None = None
        #: every tick writes, a hold's too: with gravity compensation (the default) the write's g(q) is the
        #: measured position's; without it a hold's first write would stand for the block, which no test
        #: here covers (the robots the tests run compensate), so it is not taken
        self.write_once = False
        from agentsdk.backend import Backend

        from . import PybulletBackend

        #: the calls a block makes: the backend's own (see :meth:`ready`)
        self._stock = (Backend.step, Backend.write, PybulletBackend._step, PybulletBackend._write,
                       PybulletBackend.substeps)

    def controls(self, rows: np.ndarray, setpoint: object) -> Callable[[int], None] | None:
        """None: each tick writes its setpoint through the backend (``g(q)`` needs the measured state)."""
        return None

    def ready(self) -> bool:
        """A block can run now: a fixed base without mimic joints, the backend's own calls, no contact point."""
        b = self._b
        cls = type(b)
        own = getattr(b, "__dict__", None) or {}
        if ((cls.step, cls.write, cls._step, cls._write, cls.substeps) != self._stock
                or any(name in own for name in ("step", "_step", "write", "_write", "substeps"))):
            return False
        if b._cid < 0 or b._floating_step is not None or b.floating_base or b._mimic_pairs or not b._dofs:
            return False
        return not p.getContactPoints(physicsClientId=b._cid)

    def run(self, write: Callable[[int], bool | None], count: int, readings: np.ndarray,
            stop: Callable[[], bool] | None = None, controls: Callable[[int], None] | None = None) -> int:
        """Run ticks ``0 .. count - 1``: ``write(k)``, the substeps, read into ``readings[k]`` (3, n).

        Returns the ticks done: ``count``, or fewer when a substep diverged (:attr:`fault`, PyBullet
        left as the diverged substep left it, as tick by tick), ``write(k)`` returned False (it wrote
        nothing: the block ends before tick ``k``), or a tick left a contact point (the block ends
        after it). :meth:`restore` reads tick starts from ``readings``: leave it as it is until then.
        ``stop`` and ``controls`` (an open loop, :meth:`agentsdk.block.BlockStepperLike.run`) are not
        used: every tick calls ``write``.
        """
        if not 0 <= count <= self.capacity:
            raise InvalidValueError(f"count must be within 0..{self.capacity}, got {count}")
        b = self._b
        self.fault = None
        self.done = 0
        self._at_end = True
        cid = b._cid
        contacts = p.getContactPoints
        substeps, read = b.substeps, b.read
        q_all, v_all, tau = b._q_all, b._v_all, b._tau
        qs, vs, taus, times = self._q, self._v, self._tau, self._time
        rq, rv, re = readings[:, 0], readings[:, 1], readings[:, 2]  # (one view per row kind, not per tick)
        # every dof commanded, in command order: tick k's start state is tick k - 1's reading (kept by
        # the caller until the restore), so only tick 0's is copied
        self._readings = readings if b._sel_all else None
        keep = self._readings is None
        qs[0] = q_all
        vs[0] = v_all
        taus[0] = tau
        done = count
        for k in range(count):
            if keep and k:
                qs[k] = q_all
                vs[k] = v_all
                taus[k] = tau
            times[k] = b._time
            if write(k) is False:
                done = k
                break
            try:
                substeps()
            except SimulationDiverged as exc:
                self.fault = exc
                done = k
                break
            q, v, e = read()
            rq[k] = q
            rv[k] = v
            re[k] = e
            if contacts(physicsClientId=cid):
                done = k + 1
                break
        self.done = done
        return done

    def restore(self, k: int, write: Callable[[int], object]) -> None:
        """Put PyBullet and the backend back to where they stood before tick ``k`` of the last run.

        ``write`` is not needed (every tick's start state is kept: nothing is replayed). Every tick a
        block ran started without contact points (see the module for the ones its end may leave in
        PyBullet's cache); the backend forgets a divergence with its state (stepping tick ``done``
        again diverges again, with the backend's own error, as tick by tick).
        """
        if not 0 <= k <= self.done:
            raise InvalidValueError(f"tick {k} is not within the last block (0..{self.done})")
        if k == self.done and self.fault is None and self._at_end:
            return  # the state as it stands
        self._at_end = False
        b = self._b
        prev = self._readings
        if k and prev is not None:
            q, v, tau = prev[k - 1]
        else:
            q, v, tau = self._q[k], self._v[k], self._tau[k]
        p.resetJointStatesMultiDof(b._body, b._dofs, q[:, None].tolist(), v[:, None].tolist(),
                                   physicsClientId=b._cid)
        b._q_all[...] = q
        b._v_all[...] = v
        b._ql = q.tolist()
        b._vl = v.tolist()
        b._tau[...] = tau
        b._time = float(self._time[k])
