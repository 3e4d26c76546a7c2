"""The MuJoCo backend's sensors: MJCF ``<sensor>`` elements as they are, the others added to the spec.

* ``imu``, ``accelerometer``, ``gyro``, ``orientation``, ``force_torque``, ``force``, ``torque``:
  MuJoCo sensors on a site at the sensor frame (an MJCF model's own sensors are read by name).
  MuJoCo's accelerometer already measures specific force (+g up at rest); its force and torque
  sensors give the wrench the parent exerts on the site's body, so the sign is flipped to the
  SDK's convention (the wrench the link exerts on its parent, Gazebo's ``child_to_parent``).
* ``contact``: the normal forces of the contacts touching the link's body (``mj_contactForce``);
  an MJCF ``touch`` sensor as MuJoCo computes it (its site's volume).
* ``rangefinder``: a MuJoCo rangefinder along the sensor's +x axis (an MJCF one along its site's
  +z, as written); ``lidar``: ``mj_multiRay`` in the sensor's x-y plane.
* ``camera``: a MuJoCo camera looking along the sensor's +x axis (z up), rendered offscreen
  (EGL or OSMesa, like :mod:`agentsdk.video`) in the control tick when due; depth is linearised
  to metres along the optical axis from the same render.

Sensor values come from the last physics step of the control period (``mj_step`` computes
sensors from the state at the start of each step).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from agentsdk.errors import AgentSDKError, BackendStartError
from agentsdk.sensors import SensorChannel, SensorSpec

__all__ = ["MujocoSensors"]

SERVED = frozenset({
    "imu", "accelerometer", "gyro", "orientation", "force_torque", "force", "torque", "contact", "rangefinder",
    "lidar", "camera",
})

_S = mujoco.mjtSensor
_SITE = mujoco.mjtObj.mjOBJ_SITE


def _qmul(a: Sequence[float], b: Sequence[float]) -> list[float]:
    """Hamilton product of MuJoCo quaternions (w, x, y, z)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return [
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ]


#: MuJoCo rangefinders measure along the site's +z: the site is turned so that +z is the sensor's +x
_Z_TO_X = [math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0]
#: MuJoCo cameras look along -z with y up: turned so that they look along the sensor's +x with z up
_CAM = [0.5, 0.5, -0.5, -0.5]


class MujocoSensors:
    """Adds the sensors to an ``MjSpec``, binds them to the compiled model, samples them into channels."""

    def __init__(self, specs: Sequence[SensorSpec], label: str) -> None:
        self.specs = tuple(specs)
        self.label = label
        self._readers: list[Any] = []
        self._renderer: _Renderer | None = None
        self._plans: dict[int, tuple[np.ndarray, list[tuple[int, Any, Any]]]] = {}
        self._gl_error: AgentSDKError | None = None

    # ------------------------------------------------------------ build
    def add_to(self, spec: mujoco.MjSpec) -> None:
        """Sites, sensors and cameras for every sensor the model does not already hold."""
        for s in self.specs:
            if s.source == "mjcf" or s.kind not in SERVED:
                continue
            body = spec.worldbody if s.link == "world" else spec.body(s.link)
            if body is None:
                raise BackendStartError(f"sensor {s.name!r} of {self.label}: link {s.link!r} has no MuJoCo body")
            x, y, z, w = s.quat
            quat = [w, x, y, z]
            if s.kind in ("rangefinder",):
                quat = _qmul(quat, _Z_TO_X)
            if s.kind == "camera":
                cam = body.add_camera()
                cam.name = f"agentsdk/{s.name}"
                cam.pos = list(s.xyz)
                cam.quat = _qmul(quat, _CAM)
                c = s.camera
                assert c is not None
                cam.fovy = math.degrees(2.0 * math.atan(math.tan(c.horizontal_fov / 2.0) * c.height / c.width))
                vis = spec.visual.global_
                vis.offwidth = max(int(vis.offwidth), c.width)
                vis.offheight = max(int(vis.offheight), c.height)
                continue
            site = body.add_site()
            site.name = f"agentsdk/{s.name}"
            site.pos = list(s.xyz)
            site.quat = quat
            site.group = 5  # not drawn by default
            for suffix, stype in _MJ_SENSORS.get(s.kind, ()):
                sensor = spec.add_sensor()
                sensor.name = f"agentsdk/{s.name}/{suffix}"
                sensor.type = stype
                sensor.objtype = _SITE
                sensor.objname = site.name
                if stype == _S.mjSENS_RANGEFINDER:
                    sensor.intprm[0] = 1  # the distance (what the MJCF parser sets by default)

    # ------------------------------------------------------------ bind
    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve every sensor's addresses in the compiled model (views made once)."""
        self._model, self._data = model, data
        self._readers = [self._reader(s, model, data) for s in self.specs]
        if any(s.kind == "camera" and s.active for s in self.specs):
            # the GL context is made here (the backend builds off the event loop: it takes ~0.1-0.5 s)
            # and released; the control tick makes it current in its own thread when it renders
            try:
                self._renderer = _Renderer(model)
            except AgentSDKError as exc:  # no offscreen GL here: reading a camera raises this, nothing else fails
                self._gl_error = exc
            else:
                self._renderer.warm_up(data, self._channels_for_warm_up())

    def _adr(self, model: mujoco.MjModel, name: str) -> tuple[int, int]:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
        if sid < 0:
            raise BackendStartError(f"{self.label}: MuJoCo sensor {name!r} is missing from the compiled model")
        return int(model.sensor_adr[sid]), int(model.sensor_dim[sid])

    def _view(self, model: mujoco.MjModel, data: mujoco.MjData, name: str) -> np.ndarray:
        adr, dim = self._adr(model, name)
        view: np.ndarray = data.sensordata[adr : adr + dim]
        return view

    def _reader(self, s: SensorSpec, model: mujoco.MjModel, data: mujoco.MjData) -> Any:
        kind = s.kind
        if kind not in SERVED:
            return None  # a joint sensor: the loop fills it
        if kind == "camera":
            cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, f"agentsdk/{s.name}")
            return ("camera", cid)
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, s.link) if s.link != "world" else 0
        if kind == "contact" and not (s.source == "mjcf"):
            return ("contact", int(body), np.zeros(6))
        if kind == "lidar":
            sid = mujoco.mj_name2id(model, _SITE, f"agentsdk/{s.name}")
            ray = s.ray
            assert ray is not None
            ang = np.linspace(ray.min_angle, ray.max_angle, ray.samples)
            local = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
            return ("lidar", int(sid), local, np.zeros_like(local), np.zeros(ray.samples, dtype=np.int32),
                    int(model.site_bodyid[sid]), ray)
        if s.source == "mjcf":
            view = self._view(model, data, s.name)
            return (kind, view, None)
        views = tuple(self._view(model, data, f"agentsdk/{s.name}/{suffix}") for suffix, _ in _MJ_SENSORS[kind])
        return (kind, *views)

    def _channels_for_warm_up(self) -> list[tuple[int, SensorChannel]]:
        return [(r[1], SensorChannel(s, k)) for k, (s, r) in enumerate(zip(self.specs, self._readers, strict=True))
                if r is not None and r[0] == "camera" and s.active]

    # ------------------------------------------------------------ sample
    def read(self, channels: Sequence[SensorChannel]) -> None:
        """Write every due channel's sample (copies between views made once per channel: no arrays per tick)."""
        plans = self._plans
        for ch in channels:
            if not ch.due:
                continue
            plan = plans.get(ch.index)
            if plan is None or plan[0] is not ch.values:
                plan = plans[ch.index] = (ch.values, self._plan(ch))
            for op, a, b in plan[1]:
                if op == 0:
                    np.copyto(a, b)
                elif op == 1:
                    np.negative(b, out=a)
                elif op == 2:
                    self._contact(a, b, ch.values)
                elif op == 3:
                    self._touch(b, ch.values)
                elif op == 4:
                    d = float(b[0])
                    ch.values[0] = d if 0.0 <= d <= a else math.inf  # MuJoCo: -1 when nothing is hit
                elif op == 5:
                    self._lidar(b, ch.values)
                else:
                    self._render(ch, b)

    def _plan(self, ch: SensorChannel) -> list[tuple[int, Any, Any]]:
        """The copies that write one channel's sample: (op, destination, source) with views made here."""
        r = self._readers[ch.index]
        out = ch.values
        kind = r[0]
        if kind == "imu":
            _, acc, gyro, quat = r
            return [(0, out[0:3], quat[1:4]), (0, out[3:4], quat[0:1]), (0, out[4:7], gyro), (0, out[7:10], acc)]
        if kind in ("accelerometer", "gyro"):
            return [(0, out, r[1])]
        if kind == "orientation":
            q = r[1]
            return [(0, out[0:3], q[1:4]), (0, out[3:4], q[0:1])]
        if kind == "force_torque":
            return [(1, out[0:3], r[1]), (1, out[3:6], r[2])]
        if kind in ("force", "torque"):
            return [(1, out, r[1])]
        if kind == "contact":
            if r[2] is None:  # an MJCF touch sensor
                return [(3, None, r[1])]
            return [(2, r[1], r[2])]
        if kind == "rangefinder":
            ray = ch.spec.ray
            return [(4, ray.range_max if ray is not None else math.inf, r[1])]
        if kind == "lidar":
            return [(5, None, r)]
        return [(6, None, r[1])]

    def _touch(self, view: np.ndarray, out: np.ndarray) -> None:
        f = float(view[0])
        out[0] = f
        out[1] = 1.0 if f > 0.0 else 0.0

    def _contact(self, body: int, buf: np.ndarray, out: np.ndarray) -> None:
        m, d = self._model, self._data
        total = 0.0
        n = 0
        ncon = d.ncon
        if ncon:
            geom_body = m.geom_bodyid
            contacts = d.contact
            g1s, g2s = contacts.geom1, contacts.geom2
            for i in range(ncon):
                if geom_body[g1s[i]] == body or geom_body[g2s[i]] == body:
                    mujoco.mj_contactForce(m, d, i, buf)
                    if buf[0] > 0.0:
                        total += float(buf[0])
                        n += 1
        out[0] = total
        out[1] = n

    def _lidar(self, r: Any, out: np.ndarray) -> None:
        _, sid, local, world, geomid, body, ray = r
        d = self._data
        rot = d.site_xmat[sid].reshape(3, 3)
        np.matmul(local, rot.T, out=world)
        mujoco.mj_multiRay(self._model, d, d.site_xpos[sid], world.reshape(-1), None, True, body, geomid, out,
                           None, len(out), ray.range_max)
        out[(out < 0.0) | (out > ray.range_max)] = math.inf

    def _render(self, ch: SensorChannel, cam: int) -> None:
        if self._gl_error is not None:
            raise self._gl_error
        if self._renderer is None:
            self._renderer = _Renderer(self._model)
        self._renderer.render(self._data, cam, ch)

    @property
    def rendering(self) -> bool:
        """True while an offscreen GL context is held (cameras)."""
        return self._renderer is not None

    def close(self) -> None:
        """Release the offscreen GL context (if a camera rendered); from any thread."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


_MJ_SENSORS: dict[str, tuple[tuple[str, Any], ...]] = {
    "imu": (("acc", _S.mjSENS_ACCELEROMETER), ("gyro", _S.mjSENS_GYRO), ("quat", _S.mjSENS_FRAMEQUAT)),
    "accelerometer": (("acc", _S.mjSENS_ACCELEROMETER),),
    "gyro": (("gyro", _S.mjSENS_GYRO),),
    "orientation": (("quat", _S.mjSENS_FRAMEQUAT),),
    "force_torque": (("force", _S.mjSENS_FORCE), ("torque", _S.mjSENS_TORQUE)),
    "force": (("force", _S.mjSENS_FORCE),),
    "torque": (("torque", _S.mjSENS_TORQUE),),
    "rangefinder": (("range", _S.mjSENS_RANGEFINDER),),
    "contact": (),
    "lidar": (),
}


class _Renderer:
    """Offscreen rendering of the model's cameras into camera channels (one GL context, made on first use)."""

    def __init__(self, model: mujoco.MjModel) -> None:
        from agentsdk.errors import BackendUnavailableError
        from agentsdk.video import offscreen_gl_context_class

        gl = offscreen_gl_context_class()
        if gl is None:
            raise BackendUnavailableError(
                "no offscreen OpenGL for the MuJoCo camera sensors: install EGL (Debian: libegl1 libegl-mesa0 "
                "libgl1-mesa-dri) or OSMesa (libosmesa6)"
            )
        self.model = model
        w, h = int(model.vis.global_.offwidth), int(model.vis.global_.offheight)
        self._ctx = gl(w, h)
        current = getattr(self._ctx, "as_current", None)
        scope = current() if current is not None else contextlib.nullcontext(self._ctx.make_current())
        with scope:
            self._scene = mujoco.MjvScene(model, maxgeom=10000)
            self._opt = mujoco.MjvOption()
            self._cam = mujoco.MjvCamera()
            self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        self._buffers: dict[tuple[int, int], tuple[mujoco.MjrRect, np.ndarray, np.ndarray]] = {}
        extent = float(model.stat.extent)
        self._near = float(model.vis.map.znear) * extent
        self._far = float(model.vis.map.zfar) * extent

    def warm_up(self, data: mujoco.MjData, channels: Sequence[tuple[int, SensorChannel]]) -> None:
        """Render every camera once (compiling the shaders of a software renderer takes ~0.2 s), then release."""
        current = getattr(self._ctx, "as_current", None)
        with current() if current is not None else contextlib.nullcontext():
            for cam, ch in channels:
                self.render(data, cam, ch)

    def render(self, data: mujoco.MjData, cam: int, ch: SensorChannel) -> None:
        image = ch.image
        assert image is not None
        h, w = image.shape[:2]
        bufs = self._buffers.get((w, h))
        if bufs is None:
            bufs = self._buffers[(w, h)] = (
                mujoco.MjrRect(0, 0, w, h), np.zeros((h, w, 3), np.uint8), np.zeros((h, w), np.float32),
            )
        rect, rgb, depth = bufs
        current = getattr(self._ctx, "as_current", None)
        # current only while rendering (released after): the context may render from the control loop's
        # thread or, when a camera is started, once from a worker thread
        with current() if current is not None else contextlib.nullcontext(self._ctx.make_current()):
            self._draw(data, cam, ch, rect, rgb, depth)

    def _draw(self, data: mujoco.MjData, cam: int, ch: SensorChannel, rect: Any, rgb: np.ndarray,
              depth: np.ndarray) -> None:
        image = ch.image
        assert image is not None
        self._cam.fixedcamid = cam
        mujoco.mjv_updateScene(self.model, data, self._opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        mujoco.mjr_render(rect, self._scene, self._con)
        want_depth = ch.depth is not None
        mujoco.mjr_readPixels(rgb, depth if want_depth else None, rect, self._con)
        np.copyto(image, rgb[::-1])  # OpenGL's rows run bottom-up
        if want_depth:
            assert ch.depth is not None
            # the depth buffer (0..1, non-linear) to metres along the optical axis
            near, far = self._near, self._far
            out = ch.depth
            np.copyto(out, depth[::-1])
            out *= 1.0 - near / far
            np.subtract(1.0, out, out=out)
            np.divide(near, out, out=out)

    def close(self) -> None:
        current = getattr(self._ctx, "as_current", None)
        try:
            with current() if current is not None else contextlib.nullcontext():
                self._con.free()
        finally:
            self._ctx.free()
