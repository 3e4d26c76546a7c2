"""The executor's record of one motion or stop ramp, its preallocated tick buffers, and the table of them
that the motion layer's objects share (:class:`_MotionTable`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..limits import StepLimiter
from ..loop import ControlLoop, Setpoint, StateView
from ..offload import OffloadedGoal
from ..trajectory import (
    Trajectory,
)
from ._envelope import _Envelope
from ._handle import Motion
from ._types import MotionPhase, ResultCode


class _TickBuffers:
    """Preallocated arrays of one executor's tick path (a tick allocates no arrays)."""

    __slots__ = (
        "a",
        "act",
        "actual",
        "actual_v",
        "all",
        "at",
        "bound",
        "const",
        "dev",
        "err",
        "gain",
        "mask",
        "measured",
        "none",
        "o",
        "out",
        "q",
        "qv",
        "sample",
        "sel",
        "sp_rows",
        "sp_views",
        "st_rows",
        "st_views",
        "tmp",
        "v",
        "vt",
    )

    def __init__(self, n: int) -> None:
        self.sample = np.zeros((3, n))
        # row views made once (a view is a Python object: making them per tick would allocate)
        self.q, self.vt, self.at = self.sample[0], self.sample[1], self.sample[2]
        #: the sample's position and velocity rows (written to the setpoint in one copy when unchanged)
        self.qv = self.sample[0:2]
        self.v, self.a, self.err, self.actual, self.out = (np.zeros(n) for _ in range(5))
        self.tmp, self.o, self.dev, self.gain = (np.zeros(n) for _ in range(4))
        #: the measured position and velocity of the tick (for feedback), as the rows of one array
        self.measured = np.zeros((2, n))
        self.act, self.actual_v = self.measured[0], self.measured[1]
        #: the setpoint's effort, kp, kd rows a motion writes: zero and the loop's (read-only) gains
        self.const = np.zeros((3, n))
        self.mask = np.zeros(n, dtype=bool)
        #: ``mask.tobytes()`` with every / no joint set (a bytes compare costs less than np.count_nonzero)
        self.all, self.none = np.ones(n, dtype=bool).tobytes(), self.mask.tobytes()
        #: the joints as a slice when they are consecutive, else their index array
        self.sel: Any = None
        #: views of the setpoint, state and limiter arrays made once (basic indexing makes a view each
        #: time), for the (setpoint, state, origin) objects they were made from
        self.bound: tuple[Any, Any, Any] | None = None
        self.sp_views: tuple[np.ndarray, ...] = ()
        self.st_views: tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None] = (None, None, None)
        #: views of the setpoint block's rows 0:2 (position, velocity) and 2:5 (effort, kp, kd), and of
        #: the state block's rows 0:2 (position, velocity), for consecutive joints
        self.sp_rows: tuple[np.ndarray, np.ndarray] | None = None
        self.st_rows: np.ndarray | None = None

    def selection(self, idx: np.ndarray) -> Any:
        """The joints ``idx`` as a slice when they are consecutive (basic indexing is ~4x cheaper), else ``idx``."""
        if self.sel is None:
            n = len(idx)
            start = int(idx[0]) if n else 0
            consecutive = n > 0 and bool(np.array_equal(idx, np.arange(start, start + n)))
            self.sel = slice(start, start + n) if consecutive else idx
        return self.sel

    def bind(self, idx: np.ndarray, sp: Setpoint, st: StateView, origin: np.ndarray | None, loop: ControlLoop) -> None:
        """Make the views of consecutive joints ``idx`` into ``sp``, ``st``, ``origin`` and the loop's gains."""
        sel = self.selection(idx)
        self.bound = (sp, st, origin)
        if isinstance(sel, slice):
            self.sp_views = (sp.mode[sel], sp.enabled[sel], sp.position[sel], sp.velocity[sel], sp.effort[sel],
                             sp.kp[sel], sp.kd[sel], sp.target[sel], loop.gain_p[sel], loop.gain_d[sel],
                             sp.acceleration[sel])
            self.st_views = (st.position[sel], st.velocity[sel], None if origin is None else origin[sel])
            # rows in Setpoint.FIELDS order: position, velocity | effort, kp, kd | target, acceleration
            self.sp_rows = (sp.block[0:2, sel], sp.block[2:5, sel])
            self.const[0] = 0.0
            self.const[1] = loop.gain_p[sel]
            self.const[2] = loop.gain_d[sel]
            self.st_rows = None if st.block is None else st.block[0:2, sel]
        else:
            self.sp_views = ()
            self.st_views = (None, None, None)
            self.sp_rows = None
            self.st_rows = None


@dataclass(eq=False)
class _Exec:
    """Executor state of one motion or stop ramp (lives in the control tick)."""

    motion: Motion | None
    idx: np.ndarray
    sampler: Any
    #: robot time the trajectory (or stop ramp) starts
    t0: float
    path_tol: np.ndarray
    goal_tol: np.ndarray
    goal_time: float
    goal: np.ndarray
    phase: MotionPhase = MotionPhase.FOLLOW
    stop_code: ResultCode | None = None
    stop_msg: str = ""
    des_q: np.ndarray = field(default_factory=lambda: np.zeros(0))
    des_v: np.ndarray = field(default_factory=lambda: np.zeros(0))
    des_a: np.ndarray = field(default_factory=lambda: np.zeros(0))
    on_done: Any = None
    #: sample time of the trajectory (advances at the speed scaling factor), and the last tick's time
    tau: float = 0.0
    t_last: float = 0.0
    #: speed scaling actually applied, and its rate (1/s)
    s: float = 1.0
    sdot: float = 0.0
    #: trajectory-time velocity and acceleration at ``tau`` (for the scaling ramp's bound)
    vt: np.ndarray = field(default_factory=lambda: np.zeros(0))
    at: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: continuous joints of this motion (errors wrap around), or None
    wrap: np.ndarray | None = None
    #: the trajectory to start at ``t0`` (pending motions), its tolerance options
    pending_traj: Trajectory | None = None
    stretch: bool = False
    #: the trajectory ends moving (allow_nonzero_velocity_at_end): decelerate after the end
    end_moving: bool = False
    reported_clip: bool = False
    #: the safety limiter of its joints (:meth:`StepLimiter.select`), made when it starts or on the first tick
    limits: StepLimiter | None = None
    #: what the limiter would never change of its trajectory's samples (:mod:`._envelope`), or None
    env: _Envelope | None = None
    #: every path tolerance is infinite (the path check only rejects NaN errors)
    path_unbounded: bool = False
    #: block lockstep only: a stop ramp's sampler and its envelope (None: nothing proven), made when a
    #: block first asks (the tick itself keeps the limiter's full path for stop ramps)
    ramp_env: tuple[Any, _Envelope | None] | None = None
    #: its joints as a slice when they are consecutive (basic indexing: ~4x cheaper than ``idx`` per write)
    sel: Any = None
    #: the tick path's preallocated arrays (made on the first tick)
    work: _TickBuffers | None = None
    #: the goal the backend's own controller runs instead (:mod:`agentsdk.offload`), and its desired state
    remote: OffloadedGoal | None = None
    remote_q: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: robot time since which the joints of an ended offloaded goal are still (-1: the goal runs)
    remote_rest: float = -1.0
    remote_v: np.ndarray = field(default_factory=lambda: np.zeros(0))


class _MotionTable:
    """The state the motion layer's objects share: which record drives which joint, the scheduled
    ones, the speed scaling factor, and the joints' limits they all plan with.

    One instance per :class:`~agentsdk.motion.MotionManager`, passed to the ownership, the stop
    planner, the admission and the executor (no object keeps a copy of any of it).
    """

    __slots__ = ("amax", "continuous", "owned_mask", "owner", "pending", "speed", "vmax")

    def __init__(self, loop: ControlLoop) -> None:
        joints = loop.joints
        n = len(joints)
        #: the record driving each joint (a motion or a stop ramp), or None
        self.owner: list[_Exec | None] = [None] * n
        #: motions scheduled to start later (``start_time`` in the future)
        self.pending: list[_Exec] = []
        #: joints currently driven by a record (read-only outside the ownership; changed in place only)
        self.owned_mask = np.zeros(n, dtype=bool)
        #: the speed scaling factor every trajectory follows (1.0: as timed, 0.0: paused)
        self.speed = 1.0
        #: the joints' velocity and acceleration limits (read-only)
        self.vmax = np.array([j.max_velocity for j in joints], dtype=np.float64)
        self.amax = np.array([j.max_acceleration for j in joints], dtype=np.float64)
        #: continuous joints: shortest-angle start, wrapped errors (read-only)
        self.continuous = np.array([j.type == "continuous" for j in joints], dtype=bool)
