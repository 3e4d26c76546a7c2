"""The :class:`Recorder`: an OBSERVE-phase tick hook filling preallocated blocks, written in chunks."""

from __future__ import annotations

import asyncio
import datetime as _dt
import json
import logging
import math
import os
import tempfile
import threading
import time
from collections import deque
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..backend import SetpointView
from ..errors import ConfigurationError
from ..loop import Phase, StateView
from ..statemachine import StateMachine
from ._channels import FORMAT, NS_PER_S, SAFETY_EVENTS, TRANSITIONS, stamp_ns
from ._formats import TfLayout, tf_batch
from ._reader import RunData, read_recording
from ._sink import RowChunk, Sink, TfSamples, foxglove_urdf

if TYPE_CHECKING:

    from ..robot import Robot


log = logging.getLogger("agentsdk.recording")


#: OBSERVE-phase order of the recorder: before every other observer (it sees the setpoint as written)
RECORDER_ORDER = -1000

BLOCK_TICKS = 4096
#: unwritten ticks kept in memory before the tick hook starts writing a few messages per tick
DRAIN_AFTER_TICKS = 16 * BLOCK_TICKS
#: messages written per tick while draining (more than a tick produces, so the backlog shrinks)
_DRAIN_PER_TICK = 4
#: wall-clock seconds between writes to the file: a killed run loses at most about this much
FLUSH_INTERVAL = 0.5
#: longest the writer task encodes before yielding to the event loop (s)
_SLICE_S = 0.001
#: default rate of /tf (Hz of robot time): smooth in Foxglove, cheap for a 30-link robot
TF_RATE = 50.0
#: ``--record-format`` choices
RECORD_FORMATS = ("mcap", "ros2")


# ------------------------------------------------------------------ recorder
class _Block:
    """Preallocated per-tick rows (one control tick per row)."""

    __slots__ = ("e", "en", "kd", "kp", "mode", "q", "sp_e", "sp_q", "sp_v", "t", "target", "tc", "v")

    def __init__(self, cap: int, n: int) -> None:
        self.t = np.empty(cap)
        self.tc = np.empty(cap)
        self.q = np.empty((cap, n))
        self.v = np.empty((cap, n))
        self.e = np.empty((cap, n))
        self.sp_q = np.empty((cap, n))
        self.sp_v = np.empty((cap, n))
        self.sp_e = np.empty((cap, n))
        self.kp = np.empty((cap, n))
        self.kd = np.empty((cap, n))
        self.target = np.empty((cap, n))
        self.en = np.empty((cap, n), dtype=bool)
        self.mode = np.empty((cap, n), dtype=np.int8)


_CMD_FIELDS = ("sp_q", "sp_v", "sp_e", "kp", "kd", "en", "mode", "target")


class Recorder:
    """Records one robot's joint states, applied setpoints, link transforms, safety events and transitions.

    Create with :meth:`attach` (it registers a tick hook), call :meth:`finish`
    once the run is over (writes the MCAP summary).  Data reaches the file while
    the robot runs (see "Crash safety" in the module docs).  With ``keep=True``
    :meth:`data` returns the run as arrays; it is read back from the file (a
    temporary one without ``path``), so memory does not grow with the run.

    ``format`` is ``"mcap"`` (the agentsdk format: JSON channels, Foxglove
    transforms and description) or ``"ros2"`` (a rosbag2 MCAP: CDR
    ``sensor_msgs/msg/JointState`` and ``tf2_msgs/msg/TFMessage``).
    ``tf_rate`` (Hz of robot time) decimates ``/tf``; ``None`` or 0 records no
    transforms.
    """

    def __init__(
        self,
        robot: Robot,
        path: str | os.PathLike[str] | None = None,
        *,
        rate: float | None = None,
        keep: bool = False,
        metadata: Mapping[str, str] | None = None,
        block_ticks: int = BLOCK_TICKS,
        format: str = "mcap",
        tf_rate: float | None = TF_RATE,
    ) -> None:
        if rate is not None and not (math.isfinite(rate) and rate > 0):
            raise ConfigurationError(f"record rate must be a positive number of Hz, got {rate!r}")
        if tf_rate is not None and not (math.isfinite(tf_rate) and tf_rate >= 0):
            raise ConfigurationError(f"tf rate must be a positive number of Hz (0 for none), got {tf_rate!r}")
        if format not in RECORD_FORMATS:
            raise ConfigurationError(f"unknown recording format {format!r}; choose one of {', '.join(RECORD_FORMATS)}")
        if path is None and not keep:
            raise ConfigurationError("Recorder needs a path or keep=True")
        self._robot = robot
        self.names: tuple[str, ...] = tuple(robot.joint_names)
        self.period = float(robot.control_period)
        self.rate = rate
        self.tf_rate = tf_rate or None
        self.keep = keep
        self.format = format
        self.path = Path(path) if path is not None else None
        n = len(self.names)
        self._cap = int(block_ticks)
        self._block = _Block(self._cap, n)
        self._k = 0
        self._prev_t = float(robot.clock.now())
        self.ticks = 0
        # selection state carried across blocks
        self._last_sample = math.floor(self._prev_t * rate + 1e-6) if rate else 0
        self._last_tf = math.floor(self._prev_t * self.tf_rate + 1e-6) - 1 if self.tf_rate else 0
        self._last_cmd: tuple[np.ndarray, ...] | None = None
        self._held: tuple[int, tuple[np.ndarray, ...]] | None = None
        self._event_cursor = robot.safety.event_count
        self._pending_side: list[tuple[int, str, dict[str, Any]]] = []
        self._finished = False
        self._data: RunData | None = None
        self.truncated = False
        self.metadata = self._metadata(metadata or {})
        # the kinematics (a MuJoCo model compile, ~0.2 s with its imports) is built in a thread:
        # done in the event loop it would stall a running control loop
        self._layout: TfLayout | None = None
        self._layout_thread: threading.Thread | None = None
        self._layout_ready = asyncio.Event()
        try:
            self._loop: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            self._loop = None
        self._sinks: list[Sink] = []
        self._json_path: Path | None = None
        self._temp: Path | None = None
        self._backlog: deque[tuple[RowChunk | None, list[tuple[int, str, dict[str, Any]]]]] = deque()
        self._backlog_ticks = 0
        self._drain: Iterator[None] | None = None
        self._task: asyncio.Task[None] | None = None
        self._rotated_at = time.perf_counter()
        try:
            if self.path is not None:
                self._sinks.append(Sink(self.path, ros2=format == "ros2", names=self.names, metadata=self.metadata))
                if format == "mcap":
                    self._json_path = self.path
            if keep and self._json_path is None:
                fd, tmp = tempfile.mkstemp(prefix="agentsdk-rec-", suffix=".mcap")
                os.close(fd)
                self._temp = self._json_path = Path(tmp)
                self._sinks.append(Sink(self._temp, ros2=False, names=self.names, metadata=self.metadata))
            self._write_description()
        except BaseException:
            self._close_sinks(ok=False)
            raise
        if self.tf_rate:  # started last: its imports must not hold the import lock the code above needs
            self._layout_thread = threading.Thread(
                target=self._build_layout, name="agentsdk-recorder-kinematics", daemon=True
            )
            self._layout_thread.start()
        # first observer: sees the setpoint exactly as written, before a watchdog changes it
        self._tick_handle = robot.add_tick_hook(Phase.OBSERVE, self._on_tick, order=RECORDER_ORDER)
        self._transition_handle = StateMachine.add_transition_listener(self._on_transition)

    @classmethod
    def attach(
        cls,
        robot: Robot,
        path: str | os.PathLike[str] | None = None,
        *,
        rate: float | None = None,
        keep: bool = False,
        metadata: Mapping[str, str] | None = None,
        format: str = "mcap",
        tf_rate: float | None = TF_RATE,
    ) -> Recorder:
        """Start recording ``robot`` (call right after connect, before any tick)."""
        return cls(robot, path, rate=rate, keep=keep, metadata=metadata, format=format, tf_rate=tf_rate)

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic (of ``path``'s file, or of the temporary file)."""
        return dict(self._sinks[0].counts) if self._sinks else dict(getattr(self, "_closed_counts", {}))

    # -------------------------------------------------------------- setup
    def _metadata(self, extra: Mapping[str, str]) -> dict[str, str]:
        from .. import __version__

        backend = self._robot.controller
        try:
            config = json.dumps(backend.config.model_dump(mode="json"), sort_keys=True)
        except Exception:  # pragma: no cover - a config that does not serialize
            config = ""
        opts = backend.options.model_dump(mode="json") if hasattr(backend.options, "model_dump") else {}
        md = {
            "format": FORMAT,
            "robot": self._robot.name,
            "robot_name": self._robot.name,
            "backend": self._robot.backend,
            "backend_options": json.dumps(opts, sort_keys=True),
            "realtime": "true" if self._robot.realtime else "false",
            "control_period": repr(self.period),
            "joints": json.dumps(list(self.names)),
            "record_rate": "" if self.rate is None else repr(float(self.rate)),
            "tf_rate": "" if not self.tf_rate else repr(float(self.tf_rate)),
            "robot_config": config,
            "agentsdk_version": __version__,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        }
        md.update({k: str(v) for k, v in extra.items()})
        return md

    def _build_layout(self) -> None:
        try:
            kin = self._robot.kinematics
            if tuple(kin.joint_names) != self.names:
                raise ConfigurationError("kinematics joint order differs from the robot's")
            self._layout = TfLayout(kin)
        except Exception as exc:  # a robot whose model the kinematics cannot build still records joints
            log.warning("recording without /tf: no kinematics for %s (%s)", self._robot.name, exc)
        finally:
            loop = self._loop
            if loop is not None:
                try:
                    loop.call_soon_threadsafe(self._layout_ready.set)
                except RuntimeError:  # the event loop is closed: nobody waits
                    pass

    def _layout_pending(self) -> bool:
        return self._layout_thread is not None and self._layout_thread.is_alive()

    def _join_layout(self) -> None:
        if self._layout_thread is not None:
            self._layout_thread.join()

    def _write_description(self) -> None:
        desc = getattr(self._robot, "description", None)
        urdf = getattr(desc, "urdf_xml", "") or ""
        ns = stamp_ns(self._prev_t)
        for s in self._sinks:
            if urdf:
                s.description(ns, urdf if s.ros2 else foxglove_urdf(urdf))
            s.flush()  # the header, schemas and metadata reach the disk at once

    # ----------------------------------------------------------- per tick
    def _on_tick(self, t: float, st: StateView, sp: SetpointView) -> None:
        k = self._k
        if k == self._cap:
            self._rotate()
            k = 0
        b = self._block
        b.t[k] = t
        b.tc[k] = self._prev_t
        self._prev_t = t
        b.q[k] = st.position
        b.v[k] = st.velocity
        b.e[k] = st.effort
        b.sp_q[k] = sp.position
        b.sp_v[k] = sp.velocity
        b.sp_e[k] = sp.effort
        b.kp[k] = sp.kp
        b.kd[k] = sp.kd
        b.en[k] = sp.enabled
        b.mode[k] = sp.mode
        b.target[k] = sp.target
        self._k = k + 1
        self.ticks += 1
        if self._robot.safety.event_count != self._event_cursor:
            self._take_events()
        if not (k & 15) and time.perf_counter() - self._rotated_at > FLUSH_INTERVAL:
            self._rotate()
        if self._backlog_ticks > DRAIN_AFTER_TICKS:
            self._write_some(_DRAIN_PER_TICK)

    def _take_events(self) -> None:
        safety = self._robot.safety
        new = safety.events_since(self._event_cursor)
        self._event_cursor = safety.event_count
        for ev in new:
            msg = {"kind": ev.kind, "joint": ev.joint, "detail": ev.detail}
            self._pending_side.append((stamp_ns(ev.time), SAFETY_EVENTS, msg))

    def _on_transition(self, machine: Any, rec: Any) -> None:
        if getattr(machine, "robot", None) is not self._robot or self._finished:
            return
        msg = {"machine": rec.machine, "source": rec.source, "target": rec.target, "event": rec.event, "note": rec.note}
        self._pending_side.append((stamp_ns(rec.time), TRANSITIONS, msg))

    # ----------------------------------------------------------- blocks
    def _rotate(self, final: bool = False) -> None:
        self._rotated_at = time.perf_counter()
        m = self._k
        self._k = 0
        if m == 0:
            chunk = None
            if final and self._held is not None:  # the run's last tick, held back by the previous block
                ns, row = self._held
                self._held = None
                chunk = RowChunk(
                    st_ns=np.zeros(0, np.int64), q=self._block.q[:0].copy(), v=self._block.v[:0].copy(),
                    e=self._block.e[:0].copy(), cmd_ns=np.array([ns], np.int64),
                    cmd={f: r[None] for f, r in zip(_CMD_FIELDS, row, strict=True)},
                    tf_ns=np.zeros(0, np.int64), tf_q=self._block.q[:0].copy(),
                )
            if self._pending_side or chunk is not None:
                side, self._pending_side = self._pending_side, []
                self._backlog.append((chunk, side))
                self._kick()
            return
        chunk = self._select(self._block, m, final)
        side, self._pending_side = self._pending_side, []
        self._backlog.append((chunk, side))
        self._backlog_ticks += len(chunk.st_ns)
        self._kick()

    def _select(self, b: _Block, m: int, final: bool = False) -> RowChunk:
        t = b.t[:m]
        if self.rate is None:
            st_rows = np.arange(m)
        else:
            s = np.floor(t * self.rate + 1e-6).astype(np.int64)
            prev = np.concatenate(([self._last_sample], s[:-1]))
            st_rows = np.flatnonzero(s != prev)
            self._last_sample = int(s[-1])
        if self.tf_rate:
            s = np.floor(t * self.tf_rate + 1e-6).astype(np.int64)
            prev = np.concatenate(([self._last_tf], s[:-1]))
            tf_rows = np.flatnonzero(s != prev)
            self._last_tf = int(s[-1])
        else:
            tf_rows = np.zeros(0, np.intp)
        arrays = [getattr(b, f)[:m] for f in _CMD_FIELDS]
        changed = np.zeros(m, dtype=bool)
        last = self._last_cmd
        if last is None:
            changed[0] = True
        for a, lrow in zip(arrays, last or [None] * len(arrays), strict=True):
            if m > 1:
                changed[1:] |= (a[1:] != a[:-1]).any(axis=1)
            if lrow is not None:
                changed[0] |= bool((a[0] != lrow).any())
        keep = changed.copy()
        keep[:-1] |= changed[1:]  # the last tick of a hold, so line plots stay flat
        if final:
            keep[-1] = True
        self._last_cmd = tuple(a[m - 1].copy() for a in arrays)
        cmd_rows = np.flatnonzero(keep)
        ns = np.rint(t * NS_PER_S).astype(np.int64)
        cns = np.rint(b.tc[:m] * NS_PER_S).astype(np.int64)
        # Block boundaries follow the wall clock, so they must not add messages: the last row of a
        # block is held back and written only if the next block starts with a change (or at the end)
        held, self._held = self._held, None
        if not keep[-1]:
            self._held = (int(cns[m - 1]), self._last_cmd)
        cmd = {f: a[cmd_rows] for f, a in zip(_CMD_FIELDS, arrays, strict=True)}
        cmd_ns = cns[cmd_rows]
        if held is not None and changed[0]:
            h_ns, h_row = held
            cmd = {f: np.concatenate((r[None], cmd[f])) for f, r in zip(_CMD_FIELDS, h_row, strict=True)}
            cmd_ns = np.concatenate(([h_ns], cmd_ns))
        return RowChunk(
            st_ns=ns[st_rows],
            q=b.q[st_rows],
            v=b.v[st_rows],
            e=b.e[st_rows],
            cmd_ns=cmd_ns,
            cmd=cmd,
            tf_ns=ns[tf_rows],
            tf_q=b.q[tf_rows],
        )

    # ----------------------------------------------------------- writing (off the tick)
    def _kick(self) -> None:
        """Make sure the writer task runs (it writes the backlog between ticks, then exits)."""
        if self._finished or not self._sinks or (self._task is not None and not self._task.done()):
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # not inside an event loop: finish() writes everything
            return
        self._task = loop.create_task(self._write_task(), name="agentsdk-recorder-writer")

    async def _write_task(self) -> None:
        """Write the backlog in slices of at most ``_SLICE_S`` s, yielding to the loop in between; flush at the end."""
        try:
            if self._layout_pending():
                await self._layout_ready.wait()
            while not self._finished:
                if self._write_for(_SLICE_S):
                    for s in self._sinks:
                        s.flush()
                    return
                await asyncio.sleep(0)
        except OSError as exc:
            log.error("writing the recording failed: %s", exc.strerror or exc)

    def _write_for(self, budget: float) -> bool:
        """Write backlog messages for about ``budget`` seconds; True once the backlog is empty."""
        end = time.perf_counter() + budget
        while True:
            if self._write_some(16):
                return True
            if time.perf_counter() >= end:
                return False

    def _write_some(self, n: int) -> bool:
        """Write up to ``n`` messages of the backlog (resumable); True once it is empty."""
        for _ in range(n):
            if self._drain is None:
                if not self._backlog:
                    return True
                self._drain = self._write_backlog()
            try:
                next(self._drain)
            except StopIteration:
                self._drain = None
                return not self._backlog
        return False

    def _write_backlog(self) -> Iterator[None]:
        while self._layout_pending():
            yield
        while self._backlog:
            chunk, side = self._backlog[0]
            if chunk is not None:
                tf = None
                if self._layout is not None and len(chunk.tf_ns):
                    trans = np.empty((len(chunk.tf_ns), len(self._layout.children), 3))
                    rot = np.empty((len(chunk.tf_ns), len(self._layout.children), 4))
                    for i, q in enumerate(chunk.tf_q):
                        trans[i], rot[i] = tf_batch(self._layout, q)
                        yield
                    tf = TfSamples(chunk.tf_ns, self._layout.parents, self._layout.children, trans, rot)
                for s in self._sinks:
                    yield from s.write_chunk(chunk, tf)
                self._backlog_ticks -= len(chunk.st_ns)
            for s in self._sinks:
                s.write_side(side)
            self._backlog.popleft()
            yield

    # ----------------------------------------------------------- finish
    def _close_sinks(self, ok: bool) -> None:
        sinks, self._sinks = self._sinks, []
        if sinks:  # what was written stays readable after the file is closed
            self._closed_counts = dict(sinks[0].counts)
        error: BaseException | None = None
        for s in sinks:
            try:
                s.close(ok)
            except OSError as exc:
                error = error or exc
        if error is not None:
            raise error

    def finish(self) -> None:
        """Write everything left, the MCAP summary, and close the file. Idempotent."""
        if self._finished:
            return
        self._finished = True
        self._tick_handle.remove()
        self._transition_handle.remove()
        if self._task is not None and not self._task.done():
            self._task.cancel()
        if self._robot.safety.event_count != self._event_cursor:
            self._take_events()
        self._rotate(final=True)
        self._join_layout()
        path = self.path or self._json_path
        try:
            while not self._write_some(1 << 30):
                pass
            self._close_sinks(ok=True)
        except OSError as exc:
            self._close_sinks(ok=False)
            raise ConfigurationError(f"writing recording {path} failed: {exc.strerror or exc}") from exc
        finally:
            if self._temp is not None:
                try:
                    self._data = read_recording(self._temp)
                finally:
                    self._temp.unlink(missing_ok=True)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()

    def data(self) -> RunData:
        """The recorded run (needs ``keep=True``), read back from the file; complete after :meth:`finish`."""
        if not self.keep:
            raise ConfigurationError("Recorder.data() needs keep=True")
        if self._data is not None:
            return self._data
        assert self._json_path is not None
        if not self._finished:
            self._rotate()
            self._join_layout()
            while not self._write_some(1 << 30):
                pass
            for s in self._sinks:
                s.flush()
        return read_recording(self._json_path)
