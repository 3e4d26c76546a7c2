"""The preallocated arrays one sensor's samples are written into (what a backend's ``_read_sensors`` fills)."""

from __future__ import annotations

import numpy as np

from ._spec import SensorSpec

__all__ = ["SensorChannel"]


class SensorChannel:
    """One sensor's sample buffers, reused every tick.

    A backend's ``_read_sensors(channels)`` writes, for every channel whose ``due`` flag is
    set, the sample into ``values`` (float64, :attr:`SensorSpec.size` values in the layout of
    :data:`~agentsdk.sensors.KINDS`) or, for a camera, ``image`` (uint8, height × width × 3,
    top row first) and ``depth`` (float32 metres along the optical axis, when the camera has
    depth). It must not replace the arrays (write in place) and allocates nothing it can avoid.
    """

    __slots__ = ("depth", "due", "image", "index", "spec", "values")

    def __init__(self, spec: SensorSpec, index: int) -> None:
        self.spec = spec
        #: position in ``Backend.sensors``
        self.index = index
        self.values = np.zeros(spec.size)
        cam = spec.camera
        self.image: np.ndarray | None = None
        self.depth: np.ndarray | None = None
        if spec.kind == "camera":
            assert cam is not None
            self.image = np.zeros((cam.height, cam.width, 3), dtype=np.uint8)
            if cam.depth:
                self.depth = np.zeros((cam.height, cam.width), dtype=np.float32)
        if spec.kind in ("imu", "orientation"):
            self.values[3] = 1.0  # a unit quaternion (x, y, z, w) before the first sample
        #: set by the loop: sample this channel in this tick
        self.due = True

    def __repr__(self) -> str:
        return f"<SensorChannel {self.spec.name!r} ({self.spec.kind})>"
