"""The PyBullet backend's sensors, with the same frames, units and signs as the MuJoCo backend's.

* ``imu`` / ``accelerometer`` / ``gyro`` / ``orientation``: from the link's pose and velocity
  (``getLinkState`` with link velocities; the base's from ``getBaseVelocity``), moved to the sensor
  point; the linear acceleration is the finite difference of the sensor point's velocity between
  two samples, and the reported value is the specific force ``R^T (a - g)`` (+9.81 up at rest).
* ``force_torque`` / ``force`` / ``torque``: ``enableJointForceTorqueSensor`` on the link's parent
  joint; PyBullet reports the reaction wrench in the joint frame at the child link's origin, which
  is turned into the SDK's convention (the wrench the link exerts on its parent, in the sensor frame).
* ``contact``: ``getContactPoints`` on the link, normal forces summed.
* ``rangefinder`` / ``lidar``: ``rayTestBatch`` along the sensor's +x axis / in its x-y plane.
* ``camera``: ``getCameraImage`` with TinyRenderer (CPU, headless), looking along the sensor's
  +x axis with z up; depth linearised to metres along the optical axis.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from agentsdk.errors import BackendStartError
from agentsdk.pose import Pose
from agentsdk.sensors import SensorChannel, SensorSpec

from .quiet import filtered_native_output

with filtered_native_output():
    import pybullet as p

__all__ = ["SERVED", "PybulletSensors"]

SERVED = frozenset({
    "imu", "accelerometer", "gyro", "orientation", "force_torque", "force", "torque", "contact", "rangefinder",
    "lidar", "camera",
})

_FT = ("force_torque", "force", "torque")
#: the link index of a frame that stands still at the world origin
_WORLD = -1000
_INERTIAL = ("imu", "accelerometer", "gyro", "orientation")


class _Sensor:
    __slots__ = ("dirs", "kind", "link", "offset", "prev_t", "prev_v", "spec", "to_child")

    def __init__(self, spec: SensorSpec, link: int, offset: Pose) -> None:
        self.spec = spec
        self.kind = spec.kind
        self.link = link
        self.offset = offset
        self.prev_v = np.zeros(3)
        self.prev_t = math.nan
        self.to_child: np.ndarray | None = None
        self.dirs: np.ndarray | None = None


class PybulletSensors:
    """Binds the sensors to a loaded PyBullet body and samples them into channels."""

    def __init__(self, specs: Sequence[SensorSpec], label: str) -> None:
        self.specs = tuple(specs)
        self.label = label
        self._sensors: list[_Sensor | None] = []

    def bind(self, cid: int, body: int, links: dict[str, int], gravity: Sequence[float],
             base_inertial: Pose | None, world_links: Sequence[str] = ()) -> None:
        """Resolve link indices, enable the force-torque sensors.

        ``world_links``: links PyBullet does not hold that stand still at the world origin (a floating
        robot's massless root, which MuJoCo also keeps as its world body).
        """
        self._cid, self._body = cid, body
        self._g = np.array(gravity, dtype=float)
        self._base_inertial = base_inertial if base_inertial is not None else Pose(
            *p.getDynamicsInfo(body, -1, physicsClientId=cid)[3:5]
        )
        out: list[_Sensor | None] = []
        for s in self.specs:
            if s.kind not in SERVED:
                out.append(None)
                continue
            if s.link in world_links and s.link not in links:
                links = {**links, s.link: _WORLD}
            if s.link not in links:
                raise BackendStartError(
                    f"sensor {s.name!r} of {self.label}: link {s.link!r} is not in the PyBullet model"
                )
            li = links[s.link]
            sensor = _Sensor(s, li, Pose(s.xyz, s.quat))
            if s.kind in _FT:
                if li < 0:
                    raise BackendStartError(
                        f"force-torque sensor {s.name!r} of {self.label}: link {s.link!r} is the base (it has no "
                        "parent joint to measure)"
                    )
                p.enableJointForceTorqueSensor(body, li, 1, physicsClientId=cid)
                # PyBullet reports the reaction at the child's centre of mass, in its inertial frame
                dyn = p.getDynamicsInfo(body, li, physicsClientId=cid)
                sensor.to_child = np.array(p.getMatrixFromQuaternion(dyn[4])).reshape(3, 3)
                sensor.prev_v[:] = dyn[3]  # the centre of mass in the link frame (the velocity buffer is unused)
            if s.kind == "lidar":
                ray = s.ray
                assert ray is not None
                ang = np.linspace(ray.min_angle, ray.max_angle, ray.samples)
                sensor.dirs = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
            out.append(sensor)
        self._sensors = out

    def reset(self) -> None:
        """Forget the previous velocity samples (a reset world)."""
        for s in self._sensors:
            if s is not None:
                s.prev_t = math.nan

    # ------------------------------------------------------------ sample
    def _link_frame(self, li: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(origin, rotation, com, com velocity, angular velocity) of link ``li`` in the world."""
        cid, body = self._cid, self._body
        if li == _WORLD:
            zero = np.zeros(3)
            return zero, np.eye(3), zero, zero, zero
        if li < 0:
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
            lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
            com = Pose(pos, orn)
            frame = com @ self._base_inertial.inverse()
            return frame.position, frame.rotation, np.array(pos), np.array(lin), np.array(ang)
        st = p.getLinkState(body, li, computeLinkVelocity=1, computeForwardKinematics=1, physicsClientId=cid)
        frame = Pose(st[4], st[5])
        return frame.position, frame.rotation, np.array(st[0]), np.array(st[6]), np.array(st[7])

    def read(self, channels: Sequence[SensorChannel], t: float) -> None:
        """Write every due channel's sample (``t``: the simulation time of this sample)."""
        sensors = self._sensors
        for ch in channels:
            if not ch.due:
                continue
            s = sensors[ch.index]
            if s is None:
                continue
            kind = s.kind
            out = ch.values
            if kind in _INERTIAL:
                self._inertial(s, out, t)
            elif kind in _FT:
                self._wrench(s, out)
            elif kind == "contact":
                # the link as either side of a contact (a contact with another link of the robot is listed once,
                # with the link on side A or on side B)
                total = 0.0
                n = 0
                for side in ({"bodyA": self._body, "linkIndexA": s.link}, {"bodyB": self._body, "linkIndexB": s.link}):
                    for c in p.getContactPoints(physicsClientId=self._cid, **side):
                        if c[9] > 0.0:
                            total += c[9]
                            n += 1
                out[0] = total
                out[1] = n
            elif kind in ("rangefinder", "lidar"):
                self._rays(s, out)
            elif kind == "camera":
                self._camera(s, ch)

    def _sensor_pose(self, s: _Sensor) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        origin, rot, com, v_com, omega = self._link_frame(s.link)
        off = s.offset
        r_s = rot @ off.rotation
        pos = origin + rot @ off.position
        return pos, r_s, com, v_com, omega

    def _inertial(self, s: _Sensor, out: np.ndarray, t: float) -> None:
        pos, r_s, com, v_com, omega = self._sensor_pose(s)
        kind = s.kind
        if kind in ("imu", "orientation"):
            q = Pose(pos, _quat_from_matrix(r_s)).orientation
            k = 0
            out[k : k + 4] = q
        if kind in ("imu", "gyro"):
            w = r_s.T @ omega
            if kind == "imu":
                out[4:7] = w
            else:
                out[:] = w
        if kind in ("imu", "accelerometer"):
            v = v_com + np.cross(omega, pos - com)
            dt = t - s.prev_t
            acc = (v - s.prev_v) / dt if dt > 0.0 else np.zeros(3)  # NaN prev_t: the first sample
            s.prev_v[:] = v
            s.prev_t = t
            f = r_s.T @ (acc - self._g)
            if kind == "imu":
                out[7:10] = f
            else:
                out[:] = f

    def _wrench(self, s: _Sensor, out: np.ndarray) -> None:
        react = p.getJointState(self._body, s.link, physicsClientId=self._cid)[2]
        # the wrench the parent exerts on the child at its centre of mass, turned into the link frame;
        # the SDK reports the opposite one (child on parent), about the sensor origin, in the sensor frame
        rot = s.to_child
        assert rot is not None
        f = rot @ np.array(react[0:3])
        m = rot @ np.array(react[3:6])
        com = s.prev_v
        off = s.offset
        m_origin = m + np.cross(com - off.position, f)
        rt = off.rotation.T
        f_s = -(rt @ f)
        m_s = -(rt @ m_origin)
        if s.kind == "force_torque":
            out[0:3] = f_s
            out[3:6] = m_s
        elif s.kind == "force":
            out[:] = f_s
        else:
            out[:] = m_s

    def _rays(self, s: _Sensor, out: np.ndarray) -> None:
        pos, r_s, *_ = self._sensor_pose(s)
        ray = s.spec.ray
        rmax = ray.range_max if ray is not None else 100.0
        dirs = s.dirs if s.dirs is not None else np.array([[1.0, 0.0, 0.0]])
        world = dirs @ r_s.T
        starts = np.broadcast_to(pos, world.shape)
        ends = starts + rmax * world
        hits = p.rayTestBatch(starts.tolist(), ends.tolist(), physicsClientId=self._cid)
        for k, h in enumerate(hits):
            out[k] = h[2] * rmax if h[0] >= 0 else math.inf

    def _camera(self, s: _Sensor, ch: SensorChannel) -> None:
        cam = s.spec.camera
        assert cam is not None and ch.image is not None
        pos, r_s, *_ = self._sensor_pose(s)
        target = pos + r_s[:, 0]
        up = r_s[:, 2]
        view = p.computeViewMatrix(pos.tolist(), target.tolist(), up.tolist(), physicsClientId=self._cid)
        fovy = math.degrees(2.0 * math.atan(math.tan(cam.horizontal_fov / 2.0) * cam.height / cam.width))
        proj = p.computeProjectionMatrixFOV(fovy, cam.width / cam.height, cam.near, cam.far, physicsClientId=self._cid)
        _, _, rgba, depth, _ = p.getCameraImage(
            cam.width, cam.height, view, proj, renderer=p.ER_TINY_RENDERER,
            flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=self._cid,
        )
        ch.image[:] = np.asarray(rgba, dtype=np.uint8).reshape(cam.height, cam.width, 4)[:, :, :3]
        if ch.depth is not None:
            d = np.asarray(depth, dtype=np.float64).reshape(cam.height, cam.width)
            ch.depth[:] = cam.far * cam.near / (cam.far - (cam.far - cam.near) * d)


def _quat_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """Rotation matrix -> quaternion (x, y, z, w)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax([r[0, 0], r[1, 1], r[2, 2]]))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 1e-300))
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return (q[0], q[1], q[2], q[3])

