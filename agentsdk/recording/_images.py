"""Camera frames in recordings: ``/sensors/<camera>`` as ``sensor_msgs/msg/CompressedImage`` at a low rate.

In the tick, at most ``camera_rate`` times per second of robot time, each camera's
new frame is copied into a preallocated frame pool (a few frames per camera);
the writer thread compresses it (PNG or JPEG, with Pillow) and returns the frame
to the pool.  When the pool is empty (the writer is behind) a real-time run drops
the frame (counted in :attr:`ImageTap.dropped`); a lockstep run waits for the
writer, as it does for blocks.
"""

from __future__ import annotations

import io
import math
import queue
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ._cdr import CdrWriter
from ._channels import stamp_ns
from ._sensors import SENSOR_PREFIX

if TYPE_CHECKING:
    from ..robot import Robot

__all__ = ["IMAGE_FORMATS", "IMAGE_TYPE", "ImageSeries", "ImageTap", "camera_names"]

IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
#: ``image_format`` choices (``sensor_msgs/CompressedImage.format``)
IMAGE_FORMATS = ("png", "jpeg")
#: frames per camera in the pool
_POOL = 6

#: a frame waiting for the writer: (log ns, stamp ns, camera index, pool slot)
Frame = tuple[int, int, int, int]


def camera_names(robot: Robot) -> tuple[tuple[str, str], ...]:
    """``(name, frame_id)`` of the robot's cameras."""
    sensors = getattr(robot, "sensors", None)
    return tuple((i.name, i.frame_id) for i in sensors if i.type == "camera") if sensors is not None else ()


class ImageTap:
    """The recorder's camera part: copies frames in the tick, encodes them on the writer thread."""

    def __init__(self, robot: Robot, rate: float, image_format: str, t0: float, wait: float | None) -> None:
        cams = camera_names(robot)
        sensors = robot.sensors
        self.names = tuple(n for n, _ in cams)
        self.frame_ids = tuple(f for _, f in cams)
        self.topics = tuple(SENSOR_PREFIX + n for n in self.names)
        self.rate = rate
        self.format = image_format
        views = [sensors.image_view(n) for n in self.names]
        self._views = tuple(v for v in views if v is not None)
        self._stamp: Callable[[str], float] = sensors.stamp
        self._pool = tuple(np.empty((_POOL, *v.shape), np.uint8) for v in self._views)
        self._free: tuple[queue.SimpleQueue[int], ...] = tuple(queue.SimpleQueue() for _ in self._views)
        for q in self._free:
            for k in range(_POOL):
                q.put(k)
        self._last = math.floor(t0 * rate + 1e-6)
        self._last_stamp = [-math.inf] * len(self._views)
        self._wait = wait
        #: frames waiting to be handed to the writer
        self.pending: list[Frame] = []
        #: frames not recorded because the writer was behind
        self.dropped = 0

    def tick(self, t: float) -> bool:
        """Copy the cameras' new frames if a camera sample is due; True when the writer should get them now."""
        s = math.floor(t * self.rate + 1e-6)
        if s == self._last:
            return False
        self._last = s
        for i, name in enumerate(self.names):
            st = self._stamp(name)
            if st == self._last_stamp[i] or not math.isfinite(st):  # not started, or no new frame
                continue
            try:
                k = self._free[i].get_nowait() if self._wait is None else self._free[i].get(timeout=self._wait)
            except queue.Empty:
                self.dropped += 1
                continue
            np.copyto(self._pool[i][k], self._views[i])
            self._last_stamp[i] = st
            self.pending.append((stamp_ns(t), stamp_ns(st), i, k))
        return len(self.pending) * 2 >= _POOL

    def take(self) -> list[Frame]:
        """The frames copied since the last hand-off."""
        frames, self.pending = self.pending, []
        return frames

    def encode(self, frames: list[Frame]) -> dict[str, tuple[np.ndarray, list[bytes]]]:
        """``{topic: (log ns, messages)}`` of ``frames``, compressed (writer thread); frees their pool slots."""
        from PIL import Image

        out: dict[str, tuple[list[int], list[bytes]]] = {}
        for log_ns, st_ns, i, k in frames:
            try:
                buf = io.BytesIO()
                img = Image.fromarray(self._pool[i][k], "RGB")
                if self.format == "png":
                    img.save(buf, format="PNG", compress_level=1)
                else:
                    img.save(buf, format="JPEG", quality=90)
            finally:
                self._free[i].put(k)
            w = CdrWriter()
            w.header(st_ns, self.frame_ids[i])
            w.string(self.format)
            data = buf.getvalue()
            w.u32(len(data))
            w.buf += data
            stamps, msgs = out.setdefault(self.topics[i], ([], []))
            stamps.append(log_ns)
            msgs.append(w.message())
        return {topic: (np.array(s, np.int64), m) for topic, (s, m) in out.items()}

    def release(self, frames: list[Frame]) -> None:
        """Return frames that will not be encoded (a failed writer) to the pool."""
        for _, _, i, k in frames:
            self._free[i].put(k)


@dataclass
class ImageSeries:
    """One camera's recorded frames: ``time`` (header stamps, ns), ``format`` and the compressed ``data``."""

    name: str
    frame_id: str
    format: str
    time: np.ndarray
    data: list[bytes]

    def frame(self, i: int) -> np.ndarray:
        """Frame ``i`` decoded to ``uint8`` (height × width × 3, RGB)."""
        from PIL import Image

        with Image.open(io.BytesIO(self.data[i])) as img:
            return np.asarray(img.convert("RGB"))
