"""The :class:`Recorder`: an OBSERVE-phase tick hook filling preallocated blocks; a thread writes them."""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import os
import queue
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..backend import SetpointView
from ..errors import ConfigurationError
from ..loop import Phase, StateView
from ..statemachine import StateMachine
from ..threads import run_blocking
from ..types import FloatArray
from ._channels import FORMAT, SAFETY_EVENTS, TRANSITIONS, stamp_ns
from ._images import IMAGE_FORMATS, ImageTap, camera_names
from ._reader import RunData, read_recording
from ._sensors import sensor_tracks, tracks_json
from ._writer import FLUSH_INTERVAL, Block, Job, Output, Selector, WriterThread

if TYPE_CHECKING:
    from ..kinematics import Kinematics
    from ..robot import Robot


log = logging.getLogger("agentsdk.recording")

__all__ = [
    "BLOCK_TICKS", "CAMERA_RATE", "FLUSH_INTERVAL", "RECORDER_ORDER", "RECORD_FORMATS", "SENSOR_RATE", "STATE_RATE",
    "TF_RATE", "Recorder",
]

#: OBSERVE-phase order of the recorder: before every other observer (it sees the setpoint as written)
RECORDER_ORDER = -1000

#: ticks per block (fewer for robots with many joints: a block stays under :data:`_BLOCK_BYTES`)
BLOCK_TICKS = 4096
_BLOCK_BYTES = 2 << 20
#: memory for blocks (filled and waiting for the writer, or free), allocated at attach: memory stays flat
_POOL_BYTES = 8 << 20
#: longest a lockstep tick waits for the writer to free a block before ticks are dropped (wall s)
_LOCKSTEP_WAIT = 2.0
#: default rate of /joint_states (Hz of robot time); commands are never decimated
STATE_RATE = 50.0
#: default rate of /tf (Hz of robot time): smooth in Foxglove, cheap for a 30-link robot
TF_RATE = 25.0
#: default rate of the ``/sensors/<name>`` topics (Hz of robot time; a slower sensor: each of its samples)
SENSOR_RATE = 50.0
#: default rate of the camera topics (Hz of robot time): frames are compressed on the writer thread
CAMERA_RATE = 5.0
#: ``--record-format`` choices
RECORD_FORMATS = ("mcap", "ros2")


class _BlockTap:
    """The recorder's OBSERVE hook in the form block lockstep takes (:class:`agentsdk.block.BlockObserver`)."""

    __slots__ = ("_block", "_tick")

    def __init__(self, rec: Recorder) -> None:
        self._tick = rec._on_tick
        self._block = rec._on_block

    def __call__(self, t: float, state: StateView, setpoint: SetpointView) -> None:
        self._tick(t, state, setpoint)

    def observe_block(self, ts: FloatArray, states: FloatArray, setpoints: FloatArray,
                      setpoint: SetpointView) -> None:
        self._block(ts, states, setpoints, setpoint)


class Recorder:
    """Records one robot's joint states, applied setpoints, link transforms, sensors, safety events, transitions.

    Create with :meth:`attach` (it registers a tick hook), call :meth:`finish`
    once the run is over (writes the MCAP summary).  Data reaches the file while
    the robot runs, from a writer thread; the tick hook only copies arrays into
    preallocated blocks.  With ``keep=True`` :meth:`data` returns the run as
    arrays; it is read back from the file (a temporary one without ``path``), so
    memory does not grow with the run.

    ``format`` is ``"mcap"`` (the agentsdk format: CDR messages with ``ros2msg``
    schemas, replayable) or ``"ros2"`` (standard ROS 2 message types only:
    ``/joint_commands`` as ``sensor_msgs/msg/JointState``, no safety events or
    transitions).  ``rate`` (Hz of robot time) decimates ``/joint_states``;
    ``None`` records every tick.  ``tf_rate`` decimates ``/tf``; ``None`` or 0
    records no transforms.  ``sensor_rate`` bounds the ``/sensors/<name>``
    topics (every sensor but cameras; ``None``: every tick).
    """

    def __init__(
        self,
        robot: Robot,
        path: str | os.PathLike[str] | None = None,
        *,
        rate: float | None = STATE_RATE,
        keep: bool = False,
        metadata: Mapping[str, str] | None = None,
        block_ticks: int = BLOCK_TICKS,
        format: str = "mcap",
        tf_rate: float | None = TF_RATE,
        sensor_rate: float | None = SENSOR_RATE,
        camera_rate: float | None = CAMERA_RATE,
        image_format: str = "png",
    ) -> None:
        if camera_rate is not None and not (math.isfinite(camera_rate) and camera_rate >= 0):
            raise ConfigurationError(
                f"camera record rate must be a positive number of Hz (0 for none), got {camera_rate!r}"
            )
        if image_format not in IMAGE_FORMATS:
            raise ConfigurationError(f"unknown image format {image_format!r}; choose one of {', '.join(IMAGE_FORMATS)}")
        if sensor_rate is not None and not (math.isfinite(sensor_rate) and sensor_rate > 0):
            raise ConfigurationError(f"sensor record rate must be a positive number of Hz, got {sensor_rate!r}")
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
        if rate is not None and rate * self.period >= 1.0 - 1e-9:
            rate = None  # at or above the control rate: every tick
        self.rate = rate
        self.tf_rate = tf_rate or None
        self.keep = keep
        self.format = format
        self.path = Path(path) if path is not None else None
        n = len(self.names)
        #: the recorded sensors (every one but cameras); none: the recording is exactly as without sensors
        self.sensor_tracks = sensor_tracks(robot)
        if sensor_rate is not None and sensor_rate * self.period >= 1.0 - 1e-9:
            sensor_rate = None
        self.sensor_rate = sensor_rate if self.sensor_tracks else None
        sensors = robot.sensors if self.sensor_tracks else None
        # the published arrays (updated in place by the sensor hub) and the stamp getter
        self._sensor_views = tuple(sensors.values(t.name) for t in self.sensor_tracks) if sensors else ()
        self._sensor_names = tuple(t.name for t in self.sensor_tracks)
        self._sensor_stamp = sensors.stamp if sensors else None
        width = sum(t.size for t in self.sensor_tracks)
        #: camera frames (None: no cameras, or camera_rate 0/None)
        self._images: ImageTap | None = None
        if camera_rate and camera_names(robot):
            wait = None if robot.realtime else _LOCKSTEP_WAIT
            self._images = ImageTap(robot, float(camera_rate), image_format, float(robot.clock.now()), wait)
        self.camera_rate = camera_rate if self._images is not None else None
        self.image_format = image_format
        ns = len(self.sensor_tracks)
        row = Block.row_bytes(n, width, ns)
        self._cap = max(16, min(int(block_ticks), _BLOCK_BYTES // row))
        self._free: queue.SimpleQueue[Block] = queue.SimpleQueue()
        for _ in range(max(3, _POOL_BYTES // (self._cap * row)) - 1):
            self._free.put(Block(self._cap, n, width, ns))
        self._block: Block | None = Block(self._cap, n, width, ns)
        self._k = 0
        self._prev_t = float(robot.clock.now())
        self.ticks = 0
        #: ticks not recorded because the writer fell behind and every block was in use
        self.dropped_ticks = 0
        self._gap = False
        self._event_cursor = robot.safety.event_count
        self._side: list[tuple[int, str, tuple[str | float, ...]]] = []
        self._finished = False
        self._data: RunData | None = None
        self.metadata = self._metadata(metadata or {})
        self._data_path: Path | None = None
        self._temp: Path | None = None
        #: when the last hand-off was: wall-clock (realtime) or robot time (lockstep: where a lockstep run's
        #: chunks are cut is then the same in every run of it, whatever the machine's speed)
        self._lockstep = not robot.realtime
        self._rotated_at = time.perf_counter() if robot.realtime else self._prev_t
        outputs: list[Output] = []
        try:
            if self.path is not None:
                kind = "agentsdk" if format == "mcap" else "ros2"
                outputs.append(Output(self.path, kind=kind, names=self.names, metadata=self.metadata,
                                      sensors=self.sensor_tracks, images=self._image_topics))
                if format == "mcap":
                    self._data_path = self.path
            if keep and self._data_path is None:
                fd, tmp = tempfile.mkstemp(prefix="agentsdk-rec-", suffix=".mcap")
                os.close(fd)
                self._temp = self._data_path = Path(tmp)
                outputs.append(Output(self._temp, kind="agentsdk", names=self.names, metadata=self.metadata,
                                      sensors=self.sensor_tracks, images=self._image_topics))
        except BaseException:
            for o in outputs:
                o.close(ok=False)
            if self._temp is not None:
                self._temp.unlink(missing_ok=True)
            raise
        desc = getattr(robot, "description", None)
        urdf = getattr(desc, "urdf_xml", "") or ""
        kin = self._kinematics if self.tf_rate else None
        # the thread writes the description and builds the kinematics (a MuJoCo model compile, ~0.2 s)
        self._writer = WriterThread(
            outputs,
            Selector(self._prev_t, self.rate, self.tf_rate, sensor_rate=self.sensor_rate, sensor_width=width,
                     sensor_count=ns),
            self._free,
            kinematics=kin,
            description=(stamp_ns(self._prev_t), urdf) if urdf else None,
            names=self.names,
            images=self._images,
        )
        # first observer: sees the setpoint exactly as written, before a watchdog changes it. Without
        # sensors or cameras (whose values exist only at the tick) it takes blocks of ticks too, so that
        # block lockstep keeps its blocks on a recorded robot (agentsdk.block.BlockObserver)
        hook: _BlockTap | Callable[[float, StateView, SetpointView], None] = (
            self._on_tick if self._sensor_views or self._images is not None else _BlockTap(self)
        )
        self._tick_handle = robot.add_tick_hook(Phase.OBSERVE, hook, order=RECORDER_ORDER)
        self._transition_handle = StateMachine.add_transition_listener(self._on_transition)

    def _kinematics(self) -> Kinematics:
        return self._robot.kinematics

    @classmethod
    def attach(
        cls,
        robot: Robot,
        path: str | os.PathLike[str] | None = None,
        *,
        rate: float | None = STATE_RATE,
        keep: bool = False,
        metadata: Mapping[str, str] | None = None,
        format: str = "mcap",
        tf_rate: float | None = TF_RATE,
        sensor_rate: float | None = SENSOR_RATE,
        camera_rate: float | None = CAMERA_RATE,
        image_format: str = "png",
    ) -> Recorder:
        """Start recording ``robot`` (call right after connect, before any tick)."""
        return cls(robot, path, rate=rate, keep=keep, metadata=metadata, format=format, tf_rate=tf_rate,
                   sensor_rate=sensor_rate, camera_rate=camera_rate, image_format=image_format)

    @property
    def _image_topics(self) -> tuple[str, ...]:
        return self._images.topics if self._images is not None else ()

    @property
    def dropped_frames(self) -> int:
        """Camera frames not recorded because the writer was behind (real time)."""
        return self._images.dropped if self._images is not None else 0

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic (of ``path``'s file, or of the temporary file)."""
        outs = self._writer.outputs
        return dict(outs[0].counts) if outs else dict(self._writer.final_counts)

    # -------------------------------------------------------------- setup
    def _metadata(self, extra: Mapping[str, str]) -> dict[str, str]:
        from .. import __version__

        backend = self._robot.backend
        try:
            config = json.dumps(backend.config.model_dump(mode="json"), sort_keys=True)
        except Exception:  # pragma: no cover - a config that does not serialize
            config = ""
        opts = backend.options.model_dump(mode="json") if hasattr(backend.options, "model_dump") else {}
        md = {
            "format": FORMAT,
            "robot": self._robot.name,
            "robot_name": self._robot.name,
            "backend": self._robot.backend.name,
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
        if self.sensor_tracks:
            md["sensors"] = tracks_json(self.sensor_tracks)
            md["sensor_rate"] = "" if self.sensor_rate is None else repr(float(self.sensor_rate))
        if self._images is not None:
            md["cameras"] = json.dumps([{"name": n, "frame_id": f}
                                        for n, f in zip(self._images.names, self._images.frame_ids, strict=True)])
            md["camera_rate"] = repr(float(self._images.rate))
            md["image_format"] = self._images.format
        md.update({k: str(v) for k, v in extra.items()})
        return md

    # ----------------------------------------------------------- per tick
    def _on_tick(self, t: float, st: StateView, sp: SetpointView) -> None:
        self.ticks += 1
        if self._robot.safety.event_count != self._event_cursor:
            self._take_events()
        b = self._block
        if b is None:  # every block is waiting for the writer: this tick is lost
            b = self._block = self._take_free()
            if b is None:
                self.dropped_ticks += 1
                self._prev_t = t
                return
        k = self._k
        b.t[k] = t
        b.tc[k] = self._prev_t
        self._prev_t = t
        b.q[k] = st.position
        b.v[k] = st.velocity
        b.e[k] = st.effort
        b.sp_q[k] = sp.position
        b.sp_v[k] = sp.velocity
        b.sp_a[k] = sp.acceleration
        b.sp_e[k] = sp.effort
        b.kp[k] = sp.kp
        b.kd[k] = sp.kd
        b.en[k] = sp.enabled
        b.mode[k] = sp.mode
        b.target[k] = sp.target
        if self._sensor_views:
            np.concatenate(self._sensor_views, out=b.sv[k])
            ss, stamp = b.ss[k], self._sensor_stamp
            for i, name in enumerate(self._sensor_names):
                ss[i] = stamp(name)  # type: ignore[misc]
        k += 1
        self._k = k
        if self._images is not None and self._images.tick(t):
            self._handoff()
        elif k == self._cap or (not (k & 15) and (t if self._lockstep else time.perf_counter()) - self._rotated_at
                                                      > FLUSH_INTERVAL):
            self._handoff()

    def _on_block(self, ts: FloatArray, states: FloatArray, rows: FloatArray, sp: SetpointView) -> None:
        """What ``len(ts)`` calls of :meth:`_on_tick` record, for a block of lockstep ticks (no sensors, no cameras).

        ``states`` (K, 3, n) and ``rows`` (K, 7, n, :attr:`agentsdk.loop.Setpoint.FIELDS` order) as
        :class:`agentsdk.block.BlockObserver` gets them; ``mode`` and ``enabled`` are constant over a block.
        The rows are copied a segment at a time, up to where the per-tick hook hands a block off: where
        the block fills, or at the first 16th row whose tick is :data:`FLUSH_INTERVAL` of robot time
        after the last hand-off (blocks run in lockstep only, where the flush is timed in robot time).
        """
        count = len(ts)
        self.ticks += count
        if self._robot.safety.event_count != self._event_cursor:
            self._take_events()
        i = 0
        while i < count:
            b = self._block
            if b is None:
                b = self._block = self._take_free()
                if b is None:  # the writer is behind by the whole pool (after the lockstep wait): these ticks are lost
                    self.dropped_ticks += count - i
                    self._prev_t = float(ts[count - 1])
                    return
            k = self._k
            m = min(count - i, self._cap - k)
            # due by the segment's last tick (the times rise: then from some tick on): the tick's own test,
            # in float64 as numpy's elementwise one below, so the same rounding
            due = float(ts[i + m - 1]) - self._rotated_at > FLUSH_INTERVAL
            if due:  # the first 16th row from the first tick whose flush is due
                late = np.subtract(ts[i:i + m], self._rotated_at) > FLUSH_INTERVAL
                m = min(m, ((k + int(np.argmax(late)) + 16) & ~15) - k)
            j, e = i + m, k + m
            b.t[k:e] = ts[i:j]
            b.tc[k] = self._prev_t
            b.tc[k + 1 : e] = ts[i : j - 1]
            self._prev_t = float(ts[j - 1])
            b.q[k:e] = states[i:j, 0]
            b.v[k:e] = states[i:j, 1]
            b.e[k:e] = states[i:j, 2]
            b.sp_q[k:e] = rows[i:j, 0]
            b.sp_v[k:e] = rows[i:j, 1]
            b.sp_e[k:e] = rows[i:j, 2]
            b.kp[k:e] = rows[i:j, 3]
            b.kd[k:e] = rows[i:j, 4]
            b.target[k:e] = rows[i:j, 5]
            b.sp_a[k:e] = rows[i:j, 6]
            b.en[k:e] = sp.enabled
            b.mode[k:e] = sp.mode
            self._k = e
            i = j
            if e == self._cap or (due and not (e & 15)):
                self._handoff()

    def _take_free(self) -> Block | None:
        try:
            return self._free.get_nowait()
        except queue.Empty:
            pass
        if not self._robot.realtime:
            # lockstep: the simulated robot cannot move while the loop waits, so wait for the writer
            # (back-pressure) rather than lose ticks; the wait is about one block's encoding, and kept
            # well inside the wall-clock stall watchdog's timeout
            stall = getattr(getattr(self._robot.safety, "config", None), "stall_timeout", None)
            wait = _LOCKSTEP_WAIT if stall is None else min(_LOCKSTEP_WAIT, 0.4 * float(stall))
            try:
                return self._free.get(timeout=wait)
            except queue.Empty:
                pass
        if not self._gap:
            log.warning("the recording writer fell behind: ticks are dropped until it catches up")
        self._gap = True
        return None

    def _handoff(self, final: bool = False) -> None:
        """Queue the current block (and the side messages) for the writer and take a free block."""
        self._rotated_at = self._prev_t if self._lockstep else time.perf_counter()
        side, self._side = self._side, []
        b, m = self._block, self._k
        if b is None and not side and not final:
            return
        images = self._images.take() if self._images is not None else []
        self._writer.submit(Job(b, m if b is not None else 0, side, final, self._gap, images))
        self._gap = False
        self._k = 0
        self._block = None if final else self._take_free()

    def _take_events(self) -> None:
        safety = self._robot.safety
        new = safety.events_since(self._event_cursor)
        self._event_cursor = safety.event_count
        for ev in new:
            self._side.append((stamp_ns(ev.time), SAFETY_EVENTS, (ev.kind, ev.joint or "", ev.detail)))

    def _on_transition(self, machine: Any, rec: Any) -> None:
        if getattr(machine, "robot", None) is not self._robot or self._finished:
            return
        duration = getattr(rec, "duration", None)
        fields = (rec.machine, rec.source or "", rec.target or "", rec.event or "", rec.note or "",
                  getattr(rec, "configuration", "") or "", math.nan if duration is None else float(duration))
        self._side.append((stamp_ns(rec.time), TRANSITIONS, fields))

    async def flush(self) -> None:
        """Write every tick recorded so far to the file; the recording goes on.

        Waits in a worker thread, so the control loop keeps running (and recording)
        meanwhile. When it returns, the file holds the run up to the call: a crash
        afterwards loses nothing before it, and another process can read it.
        """
        if self._finished:
            return
        self._handoff()
        await run_blocking(self._writer.wait_written, self._writer.submitted, name="agentsdk-recorder-flush")

    # ----------------------------------------------------------- finish
    def finish(self) -> None:
        """Write everything left, the MCAP summary, and close the file. Idempotent.

        Waits for the writer thread: call it once the robot is closed (as the CLI does).
        """
        if self._finished:
            return
        self._finished = True
        self._tick_handle.remove()
        self._transition_handle.remove()
        if self._robot.safety.event_count != self._event_cursor:
            self._take_events()
        self._handoff(final=True)
        self._writer.stop()
        path = self.path or self._data_path
        error = self._writer.error
        try:
            self._writer.close_outputs(ok=error is None)
        except OSError as exc:
            error = error or exc
        if self.dropped_ticks:
            log.warning("the recording lost %d ticks: the writer fell behind", self.dropped_ticks)
        try:
            if error is not None:
                detail = getattr(error, "strerror", None) or error
                raise ConfigurationError(f"writing recording {path} failed: {detail}") from error
            if self._temp is not None:
                self._data = read_recording(self._temp)
        finally:
            if self._temp is not None:
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
        assert self._data_path is not None
        if not self._finished:
            self._handoff()
            self._writer.wait_idle()
        return read_recording(self._data_path)
