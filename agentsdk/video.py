"""Headless video of a run: ``agentsdk run ... --video run.mp4`` (or ``.gif``).

During the run a tick hook stores the robot's configuration at the video frame rate (of
robot time): a copy of a few floats, so the control loop is not slowed down. After the
run the frames are rendered offscreen and encoded, with a progress bar:

* **mujoco** backend: the backend's own model and full ``qpos`` (a floating base included),
  drawn by MuJoCo's renderer on an offscreen OpenGL context, EGL or OSMesa (no display
  needed; on Debian ``libegl1 libegl-mesa0 libgl1-mesa-dri`` or ``libosmesa6``);
* **pybullet** backend: PyBullet's CPU renderer (TinyRenderer) in a private ``DIRECT``
  client holding the same URDF;
* **mock**, **can** and any other backend: the robot drawn from its measured joint positions
  (forward kinematics of the description), with MuJoCo's renderer, or TinyRenderer when no
  offscreen OpenGL is available.

``.mp4`` is H.264 through the ffmpeg binary shipped in the ``imageio-ffmpeg`` wheel;
``.gif`` is written by Pillow. The camera looks at the robot from the front-left, framed on
its extent at the first frame.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import logging
import math
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import BackendUnavailableError, ConfigurationError

if TYPE_CHECKING:
    from .robot import Robot

__all__ = ["VIDEO_SUFFIXES", "VideoRecorder", "check_video_path", "offscreen_gl_context_class"]

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".gif")


def check_video_path(path: str | os.PathLike[str]) -> Path:
    """The output path, checked: a .mp4 or .gif file in an existing directory."""
    p = Path(path)
    if p.suffix.lower() not in VIDEO_SUFFIXES:
        raise ConfigurationError(f"--video {path}: the file must end in .mp4 or .gif")
    if p.is_dir():
        raise ConfigurationError(f"--video {path} is a directory; give a file name")
    if not p.resolve().parent.is_dir():
        raise ConfigurationError(f"cannot write video {path}: directory {p.resolve().parent} does not exist")
    return p


# --------------------------------------------------------------------------- offscreen OpenGL


_GL_STATE: dict[str, Any] = {}


def _gl_context_class() -> Any:
    """MuJoCo's offscreen GL context class (EGL, else OSMesa), or None when neither works here.

    PyOpenGL binds one platform per process, so the choice is made once: ``MUJOCO_GL`` when set
    to ``egl`` or ``osmesa``, else EGL if libEGL is present, else OSMesa.
    """
    if "cls" in _GL_STATE:
        return _GL_STATE["cls"]
    wanted = os.environ.get("MUJOCO_GL", "").lower()
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    order = ["egl", "osmesa"]
    if wanted in order:
        order.remove(wanted)
        order.insert(0, wanted)
    if platform in order:  # OpenGL may already be bound to this platform
        order = [platform]
    cls = None
    for name in order:
        lib = "EGL" if name == "egl" else "OSMesa"
        if ctypes.util.find_library(lib) is None:
            continue
        try:
            if name == "egl":
                from mujoco.egl import GLContext
            else:
                from mujoco.osmesa import GLContext
            ctx = GLContext(16, 16)
            ctx.make_current()
            ctx.free()
        except Exception as exc:  # no usable device / driver: try the next one
            log.debug("offscreen OpenGL via %s unavailable: %s", name, exc)
            continue
        cls = GLContext
        break
    _GL_STATE["cls"] = cls
    return cls


def offscreen_gl_context_class() -> Any:
    """MuJoCo's offscreen GL context class (EGL, else OSMesa; ``MUJOCO_GL`` picks first), or None when neither works."""
    return _gl_context_class()


class _MujocoRenderer:
    """Renders ``qpos`` vectors of one MjModel offscreen."""

    def __init__(self, model: Any, width: int, height: int) -> None:
        import mujoco

        gl = _gl_context_class()
        if gl is None:
            raise BackendUnavailableError(
                "no offscreen OpenGL for MuJoCo's renderer: install EGL (Debian: libegl1 libegl-mesa0 "
                "libgl1-mesa-dri) or OSMesa (libosmesa6)"
            )
        self.model = model
        self.data = mujoco.MjData(model)
        self.width, self.height = width, height
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        # URDF models carry no lights: a brighter headlight than MuJoCo's default
        model.vis.headlight.ambient[:] = np.maximum(model.vis.headlight.ambient, 0.35)
        model.vis.headlight.diffuse[:] = np.maximum(model.vis.headlight.diffuse, 0.65)
        self._ctx = gl(width, height)
        self._ctx.make_current()
        self._scene = mujoco.MjvScene(model, maxgeom=10000)
        self._opt = mujoco.MjvOption()
        self._cam = mujoco.MjvCamera()
        self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._rgb = np.zeros((height, width, 3), dtype=np.uint8)
        self._framed = False
        # a model with its own floor (a floating base's ground plane, an MJCF scene's floor) is drawn as it
        # is: a second plane in the same place flickers between the two (large grey triangles)
        plane = int(mujoco.mjtGeom.mjGEOM_PLANE)
        self._has_floor = any(
            int(model.geom_type[g]) == plane and int(model.body_weldid[model.geom_bodyid[g]]) == 0
            for g in range(model.ngeom)
        )

    def _frame_camera(self) -> None:
        import mujoco

        m, d = self.model, self.data
        bodies = np.arange(1, m.nbody)
        pts = d.xpos[bodies] if len(bodies) else np.zeros((1, 3))
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        center = (lo + hi) / 2
        extent = max(float(np.linalg.norm(hi - lo)), 0.3)
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        self._cam.lookat[:] = center
        self._cam.distance = 1.3 * extent + 0.2
        self._cam.azimuth = 135.0
        self._cam.elevation = -20.0
        self._floor_z = min(float(lo[2]), 0.0)
        self._floor_size = 2.0 * extent
        self._framed = True

    def _add_floor(self) -> None:
        """A grey ground plane under the robot (the scene has no skybox: the background stays black)."""
        import mujoco

        scn = self._scene
        if scn.ngeom >= scn.maxgeom or self._has_floor:
            return
        size = self._floor_size
        mujoco.mjv_initGeom(scn.geoms[scn.ngeom], int(mujoco.mjtGeom.mjGEOM_PLANE), np.array([size, size, 0.05]),
                            np.array([*self._cam.lookat[:2], self._floor_z]), np.eye(3).reshape(-1),
                            np.array([0.75, 0.77, 0.8, 1.0], dtype=np.float32))
        scn.ngeom += 1

    def render(self, qpos: np.ndarray) -> np.ndarray:
        import mujoco

        m, d = self.model, self.data
        d.qpos[:] = qpos
        mujoco.mj_forward(m, d)
        if not self._framed:
            self._frame_camera()
        self._ctx.make_current()
        mujoco.mjv_updateScene(m, d, self._opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        self._add_floor()
        mujoco.mjr_render(self._rect, self._scene, self._con)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, self._con)
        return np.flipud(self._rgb).copy()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._con.free()
        with contextlib.suppress(Exception):
            self._ctx.free()


def _visual_mujoco_model(description: Any) -> Any:
    """The description compiled by MuJoCo with its meshes (as the mujoco backend does), for drawing."""
    import mujoco

    from .hostmodel import mjcf_source

    mjcf = mjcf_source(description)
    if mjcf is not None:
        return mujoco.MjModel.from_xml_path(str(mjcf))
    spec = mujoco.MjSpec.from_string(description.urdf_xml)
    files = {p.name: p for p in description.mesh_files}
    for mesh in spec.meshes:
        path = files.get(Path(mesh.file).name)
        if path is None:
            continue
        mesh.file = str(_mujoco_mesh(path))
    spec.compiler.balanceinertia = True
    spec.compiler.boundmass = 1e-9
    spec.compiler.boundinertia = 1e-12
    try:
        return spec.compile()
    except Exception:  # inertials MuJoCo rejects do not matter for drawing: take them from the shapes
        spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
        return spec.compile()


def _mujoco_mesh(path: Path) -> Path:
    """``path`` itself when MuJoCo reads it (STL, OBJ, MSH), else an STL copy (COLLADA...) in a cache dir."""
    if path.suffix.lower() in (".stl", ".obj", ".msh"):
        return path
    import hashlib

    import trimesh

    digest = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:12]
    out = Path(tempfile.gettempdir()) / "agentsdk-video-meshes" / f"{path.stem}-{digest}.stl"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(f".{os.getpid()}.stl")
        trimesh.load(path, force="mesh").export(tmp)  # type: ignore[no-untyped-call]
        tmp.replace(out)  # atomic: concurrent runs never read a half-written file
    return out


class _PybulletRenderer:
    """Renders joint configurations with PyBullet's TinyRenderer (CPU, no display)."""

    def __init__(self, description: Any, names: tuple[str, ...], width: int, height: int) -> None:
        from agentsdk.backends.pybullet.quiet import filtered_native_output

        with filtered_native_output():  # no "pybullet build time: ..." on the user's terminal
            import pybullet as p

        from .hostmodel import mjcf_source

        if mjcf_source(description) is not None:
            raise BackendUnavailableError("PyBullet's renderer draws URDF robots only; this robot is MJCF")
        self._p = p
        self.width, self.height = width, height
        self._cid = p.connect(p.DIRECT)
        fd, tmp = tempfile.mkstemp(suffix=".urdf", prefix="agentsdk-video-")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(description.urdf_xml.replace("><", ">\n<"))
            self._body = p.loadURDF(tmp, useFixedBase=True, physicsClientId=self._cid)
        finally:
            Path(tmp).unlink(missing_ok=True)
        index = {}
        for i in range(p.getNumJoints(self._body, physicsClientId=self._cid)):
            info = p.getJointInfo(self._body, i, physicsClientId=self._cid)
            index[info[1].decode()] = i
        self._joints = [index.get(n, -1) for n in names]
        self._mimic = [
            (index[r.name], names.index(r.mimic), r.mimic_multiplier, r.mimic_offset)
            for r in getattr(description, "all_joints", ())
            if r.mimic and r.name in index and r.mimic in names
        ]
        self._view: Any = None
        self._proj: Any = None

    def _frame_camera(self) -> None:
        p, cid = self._p, self._cid
        lo, hi = np.array(p.getAABB(self._body, -1, physicsClientId=cid))
        for i in range(p.getNumJoints(self._body, physicsClientId=cid)):
            a, b = np.array(p.getAABB(self._body, i, physicsClientId=cid))
            lo, hi = np.minimum(lo, a), np.maximum(hi, b)
        center = (lo + hi) / 2
        extent = max(float(np.linalg.norm(hi - lo)), 0.3)
        self._view = p.computeViewMatrixFromYawPitchRoll(center.tolist(), 1.3 * extent + 0.2, 135.0 - 90.0, -20.0,
                                                         0.0, 2, physicsClientId=cid)
        self._proj = p.computeProjectionMatrixFOV(45.0, self.width / self.height, 0.05, 20.0, physicsClientId=cid)

    def render(self, q: np.ndarray) -> np.ndarray:
        p, cid = self._p, self._cid
        for k, j in enumerate(self._joints):
            if j >= 0:
                p.resetJointState(self._body, j, float(q[k]), physicsClientId=cid)
        for j, leader, mult, off in self._mimic:
            p.resetJointState(self._body, j, mult * float(q[leader]) + off, physicsClientId=cid)
        if self._view is None:
            self._frame_camera()
        _, _, rgba, _, _ = p.getCameraImage(self.width, self.height, self._view, self._proj,
                                             renderer=p.ER_TINY_RENDERER, physicsClientId=cid)
        return np.asarray(rgba, dtype=np.uint8).reshape(self.height, self.width, 4)[:, :, :3].copy()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._p.disconnect(self._cid)


# --------------------------------------------------------------------------- the recorder


class VideoRecorder:
    """Captures a run's configurations at ``fps`` (robot time) and writes them as a video on :meth:`finish`."""

    def __init__(self, robot: Robot, path: str | os.PathLike[str], *, fps: float = 30.0,
                 size: tuple[int, int] = (640, 480)) -> None:
        self.path = check_video_path(path)
        if not (math.isfinite(fps) and 1.0 <= fps <= 240.0):
            raise ConfigurationError(f"video fps must be between 1 and 240, got {fps!r}")
        w, h = size
        if not (16 <= w <= 4096 and 16 <= h <= 4096):
            raise ConfigurationError(f"video size must be between 16x16 and 4096x4096, got {w}x{h}")
        self.size = (int(w) // 2 * 2, int(h) // 2 * 2)  # H.264 (yuv420p) needs even sizes
        self.fps = float(fps)
        self.robot = robot
        ctl = robot.backend
        self._ctl = ctl
        self._names = tuple(robot.joint_names)
        self._description = ctl.description
        self.backend = robot.backend.name
        # on MuJoCo, frames are the backend's own qpos (a floating base and passive joints included),
        # drawn with its own model: MujocoBackend's public ``model`` and ``data``
        self._mj_model = getattr(ctl, "model", None) if robot.backend.name == "mujoco" else None
        self._mj_data: Any = getattr(ctl, "data", None) if self._mj_model is not None else None
        self.frames: list[np.ndarray] = []
        self._next = 0.0
        self._attached = False
        self._handle: Any = None

    @classmethod
    def attach(cls, robot: Robot, path: str | os.PathLike[str], **kw: Any) -> VideoRecorder:
        """Start capturing now (a frame every 1/fps s of robot time, from the next control tick)."""
        rec = cls(robot, path, **kw)
        rec._next = robot.clock.now()
        from .loop import Phase

        # observe, after the state is read (the recorder captures; rendering happens after the run)
        rec._handle = robot.add_tick_hook(Phase.OBSERVE, lambda t, state, setpoint: rec._on_tick(t, state))
        rec._attached = True
        return rec

    def _on_tick(self, t: float, state: Any) -> None:
        if t + 1e-9 < self._next:
            return
        self._next += 1.0 / self.fps
        if self._next <= t:  # a gap (e.g. realtime overrun): resume the cadence from now
            self._next = t + 1.0 / self.fps
        if self._mj_model is not None:
            self.frames.append(np.array(self._mj_data.qpos, dtype=float))
        else:
            self.frames.append(np.array(state.position, dtype=float))

    def detach(self) -> None:
        """Stop capturing."""
        if self._attached:
            if self._handle is not None:
                self._handle.remove()
            self._attached = False

    def _renderer(self) -> tuple[Any, Callable[[np.ndarray], np.ndarray] | None]:
        """The renderer for this backend and a mapping from captured frames to its input."""
        w, h = self.size
        if self.backend != "pybullet" and _gl_context_class() is not None:
            if self._mj_model is not None:
                return _MujocoRenderer(self._mj_model, w, h), None
            model = _visual_mujoco_model(self._description)
            return _MujocoRenderer(model, w, h), self._qpos_mapper(model)
        # PyBullet's CPU renderer: the pybullet backend, or no offscreen OpenGL on this machine
        renderer = _PybulletRenderer(self._description, self._names, w, h)
        if self._mj_model is None:
            return renderer, None
        import mujoco

        m = self._mj_model
        adr = np.array([m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in self._names])
        return renderer, lambda qpos: qpos[adr]

    def _qpos_mapper(self, model: Any) -> Callable[[np.ndarray], np.ndarray]:
        import mujoco

        adr = []
        for n in self._names:
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)
            adr.append(int(model.jnt_qposadr[jid]) if jid >= 0 else -1)
        mimic = []
        for r in getattr(self._description, "all_joints", ()):
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, r.name)
            if r.mimic and jid >= 0 and r.mimic in self._names:
                mimic.append((int(model.jnt_qposadr[jid]), self._names.index(r.mimic), r.mimic_multiplier,
                              r.mimic_offset))
        qpos0 = np.array(model.qpos0)

        def to_qpos(q: np.ndarray) -> np.ndarray:
            out = qpos0.copy()
            for k, a in enumerate(adr):
                if a >= 0:
                    out[a] = q[k]
            for a, leader, mult, off in mimic:
                out[a] = mult * q[leader] + off
            return out

        return to_qpos

    def _images(self) -> Iterator[np.ndarray]:
        renderer, mapper = self._renderer()
        try:
            for q in self.frames:
                yield renderer.render(mapper(q) if mapper is not None else q)
        finally:
            renderer.close()

    def finish(self, progress: bool = False) -> Path:
        """Render and encode the captured frames; returns the file written."""
        self.detach()
        if not self.frames:
            raise ConfigurationError("--video: the run ended before the first frame was captured")
        bar: Any = None
        task: Any = None
        if progress:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            bar = Progress(TextColumn(f"encoding {self.path.name}"), BarColumn(), MofNCompleteColumn(),
                           TimeRemainingColumn(), transient=True)
            bar.start()
            task = bar.add_task("video", total=len(self.frames))

        def tick() -> None:
            if bar is not None:
                bar.advance(task)

        try:
            if self.path.suffix.lower() == ".gif":
                self._write_gif(tick)
            else:
                self._write_mp4(tick)
        finally:
            if bar is not None:
                bar.stop()
        return self.path

    def _write_mp4(self, tick: Callable[[], None]) -> None:
        import subprocess

        import imageio_ffmpeg

        w, h = self.size
        cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
               "-s", f"{w}x{h}", "-r", f"{self.fps:g}", "-i", "-", "-an", "-c:v", "libx264", "-pix_fmt", "yuv420p",
               "-crf", "23", "-movflags", "+faststart", str(self.path)]
        with tempfile.TemporaryFile() as errors, subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=errors) as proc:
            assert proc.stdin is not None
            try:
                for img in self._images():
                    proc.stdin.write(np.ascontiguousarray(img, dtype=np.uint8).tobytes())
                    tick()
            except BrokenPipeError:
                pass  # ffmpeg died: its message is reported below
            finally:
                with contextlib.suppress(BrokenPipeError):
                    proc.stdin.close()
            code = proc.wait()
            if code != 0:
                errors.seek(0)
                detail = errors.read().decode(errors="replace").strip()
                raise ConfigurationError(f"ffmpeg could not encode {self.path} (exit {code}): {detail}")

    def _write_gif(self, tick: Callable[[], None]) -> None:
        from PIL import Image

        images = []
        for img in self._images():
            images.append(Image.fromarray(img).convert("P", palette=Image.Palette.ADAPTIVE, colors=128))
            tick()
        images[0].save(self.path, save_all=True, append_images=images[1:], duration=round(1000 / self.fps),
                       loop=0, optimize=False)
