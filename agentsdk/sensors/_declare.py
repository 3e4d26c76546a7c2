"""Sensors declared by a robot description and its robot.yaml, as :class:`SensorSpec` values.

Three sources, later ones replacing earlier ones of the same name:

1. the description: an MJCF model's ``<sensor>`` elements as they are, or a URDF's Gazebo
   ``<gazebo reference="..."><sensor type="imu|force_torque|contact|camera|depth|ray|...">``
   and ros2_control ``<sensor>`` blocks (typed by their state interfaces);
2. the robot.yaml ``sensors:`` section (name, type, link or joint, rate, noise, limits).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from ..errors import ConfigurationError
from ._spec import JOINT_KINDS, CameraSpec, RaySpec, SensorKind, SensorLimits, SensorSpec, SensorYaml

if TYPE_CHECKING:
    from ..config import RobotConfig
    from ..description import RobotDescription

__all__ = ["declared_sensors"]

log = logging.getLogger("agentsdk.sensors")


def declared_sensors(description: RobotDescription, config: RobotConfig) -> tuple[SensorSpec, ...]:
    """Every sensor the description and the robot.yaml declare, in declaration order, names unique.

    Raises :class:`~agentsdk.errors.ConfigurationError` naming the robot.yaml entry that is invalid
    (unknown type, link or joint; a joint sensor without a joint).
    """
    found: dict[str, SensorSpec] = {}
    if description.format == "mjcf":
        for spec in _mjcf_sensors(str(description.source)):
            found[spec.name] = spec
    elif description.urdf_xml:
        for spec in _urdf_sensors(description):
            found.setdefault(spec.name, spec)
    for spec in _yaml_sensors(config, description):
        found[spec.name] = spec
    return tuple(found.values())


# --------------------------------------------------------------------------- MJCF
@functools.lru_cache(maxsize=16)
def _mjcf_sensors(path: str) -> tuple[SensorSpec, ...]:
    import mujoco

    model = mujoco.MjModel.from_xml_path(path)
    t = mujoco.mjtSensor
    kinds: dict[int, SensorKind] = {
        int(t.mjSENS_ACCELEROMETER): "accelerometer",
        int(t.mjSENS_GYRO): "gyro",
        int(t.mjSENS_FRAMEQUAT): "orientation",
        int(t.mjSENS_FORCE): "force",
        int(t.mjSENS_TORQUE): "torque",
        int(t.mjSENS_TOUCH): "contact",
        int(t.mjSENS_RANGEFINDER): "rangefinder",
        int(t.mjSENS_JOINTPOS): "joint_position",
        int(t.mjSENS_JOINTVEL): "joint_velocity",
        int(t.mjSENS_ACTUATORFRC): "joint_effort",
        int(t.mjSENS_JOINTACTFRC): "joint_effort",
    }
    obj = mujoco.mjtObj
    specs: list[SensorSpec] = []
    for i in range(model.nsensor):
        kind = kinds.get(int(model.sensor_type[i]))
        name = mujoco.mj_id2name(model, obj.mjOBJ_SENSOR, i) or f"sensor{i}"
        if kind is None:
            log.debug("MJCF sensor %r of type %s is not one agentsdk reads; left out", name,
                      mujoco.mjtSensor(int(model.sensor_type[i])).name)
            continue
        objtype, objid = int(model.sensor_objtype[i]), int(model.sensor_objid[i])
        joint: str | None = None
        site: str | None = None
        xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
        quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
        if objtype == obj.mjOBJ_SITE:
            site = mujoco.mj_id2name(model, obj.mjOBJ_SITE, objid)
            body = int(model.site_bodyid[objid])
            xyz = tuple(float(x) for x in model.site_pos[objid])  # type: ignore[assignment]
            w, x, y, z = (float(v) for v in model.site_quat[objid])
            if kind == "rangefinder":
                # MuJoCo's rangefinder looks along the site's +z; the SDK's sensor frame looks along +x
                c = math.sqrt(0.5)
                w, x, y, z = (c * (w + y), c * (x + z), c * (y - w), c * (z - x))
            quat = (x, y, z, w)
        elif objtype == obj.mjOBJ_JOINT:
            joint = mujoco.mj_id2name(model, obj.mjOBJ_JOINT, objid)
            body = int(model.jnt_bodyid[objid])
        elif objtype == obj.mjOBJ_ACTUATOR:
            jid = int(model.actuator_trnid[objid, 0])
            if int(model.actuator_trntype[objid]) != int(mujoco.mjtTrn.mjTRN_JOINT):
                continue
            joint = mujoco.mj_id2name(model, obj.mjOBJ_JOINT, jid)
            body = int(model.jnt_bodyid[jid])
        elif objtype == obj.mjOBJ_BODY or objtype == obj.mjOBJ_XBODY:
            body = objid
        else:
            continue
        link = mujoco.mj_id2name(model, obj.mjOBJ_BODY, body) or "world"
        specs.append(SensorSpec(
            name=name, kind=kind, link=link, joint=joint, xyz=xyz, quat=quat,
            noise=float(model.sensor_noise[i]), source="mjcf", site=site,
        ))
    return tuple(specs)


# --------------------------------------------------------------------------- URDF
_GAZEBO_TYPES: dict[str, SensorKind] = {
    "imu": "imu",
    "force_torque": "force_torque",
    "contact": "contact",
    "camera": "camera",
    "depth": "camera",
    "depth_camera": "camera",
    "rgbd_camera": "camera",
    "ray": "lidar",
    "gpu_ray": "lidar",
    "lidar": "lidar",
    "gpu_lidar": "lidar",
}


def _text(elem: Any, path: str) -> str | None:
    found = elem.find(path)
    if found is None or found.text is None:
        return None
    return str(found.text).strip()


def _float(elem: Any, path: str, default: float) -> float:
    text = _text(elem, path)
    if text is None:
        return default
    try:
        value = float(text)
    except ValueError:
        return default
    return value if math.isfinite(value) else default


def _quat_rpy(r: float, p: float, y: float) -> tuple[float, float, float, float]:
    from ..description.model import quat_from_rpy

    w, x, yy, z = quat_from_rpy((r, p, y))
    return (x, yy, z, w)


def _urdf_sensors(description: RobotDescription) -> list[SensorSpec]:
    from lxml import etree

    from ..description.urdf import xml_parser

    try:
        root = etree.fromstring(description.urdf_xml.encode("utf-8"), xml_parser())
    except etree.XMLSyntaxError:
        return []
    links = set(description.links)
    joints = {j.name: j for j in description.all_joints}
    specs: list[SensorSpec] = []
    for gz in root.iter("gazebo"):
        ref = gz.get("reference")
        for sensor in gz.findall("sensor"):
            spec = _gazebo_sensor(sensor, ref, links, joints)
            if spec is not None:
                specs.append(spec)
    for block in root.iter("ros2_control"):
        for sensor in block.findall("sensor"):
            spec = _ros2_control_sensor(sensor, links)
            if spec is not None:
                specs.append(spec)
    return specs


def _gazebo_sensor(sensor: Any, ref: str | None, links: set[str], joints: Mapping[str, Any]) -> SensorSpec | None:
    gtype = (sensor.get("type") or "").strip()
    kind = _GAZEBO_TYPES.get(gtype)
    name = sensor.get("name") or f"{ref}_{gtype}"
    if kind is None or ref is None:
        log.debug("Gazebo sensor %r (type %r, reference %r) is not one agentsdk reads; left out", name, gtype, ref)
        return None
    joint: str | None = None
    if ref in links:
        link = ref
    elif ref in joints:
        joint, link = ref, joints[ref].child
    else:
        log.warning("Gazebo sensor %r refers to %r, which is neither a link nor a joint; left out", name, ref)
        return None
    rate_value = _float(sensor, "update_rate", 0.0)
    pose = (_text(sensor, "pose") or "").split()
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    if len(pose) == 6:
        try:
            vals = [float(v) for v in pose]
            xyz = (vals[0], vals[1], vals[2])
            quat = _quat_rpy(vals[3], vals[4], vals[5])
        except ValueError:
            pass
    noise = 0.0
    bias = 0.0
    for elem in sensor.iter("noise"):
        noise = max(noise, _float(elem, "stddev", 0.0))
        bias = bias or _float(elem, "bias_mean", 0.0) or _float(elem, "mean", 0.0)
    camera = ray = None
    if kind == "camera":
        cam = sensor.find("camera")
        cam = cam if cam is not None else sensor
        camera = CameraSpec(
            width=int(_float(cam, "image/width", 320)), height=int(_float(cam, "image/height", 240)),
            horizontal_fov=_float(cam, "horizontal_fov", 1.047), near=_float(cam, "clip/near", 0.05),
            far=_float(cam, "clip/far", 50.0), depth=gtype in ("depth", "depth_camera", "rgbd_camera"),
        )
    elif kind == "lidar":
        r = sensor.find("ray")
        if r is None:
            r = sensor.find("lidar")
        r = r if r is not None else sensor
        samples = int(_float(r, "scan/horizontal/samples", 1))
        lo, hi = _float(r, "scan/horizontal/min_angle", 0.0), _float(r, "scan/horizontal/max_angle", 0.0)
        ray = RaySpec(samples=max(samples, 1), min_angle=lo, max_angle=hi,
                      range_min=_float(r, "range/min", 0.05), range_max=_float(r, "range/max", 10.0))
        if samples <= 1:
            kind = "rangefinder"
    return SensorSpec(
        name=name, kind=kind, link=link, joint=joint, xyz=xyz, quat=quat,
        rate=rate_value if rate_value > 0 else None, noise=noise, bias=bias, source="gazebo",
        camera=camera, ray=ray, active=kind != "camera",
    )


def _ros2_control_sensor(sensor: Any, links: set[str]) -> SensorSpec | None:
    name = sensor.get("name") or ""
    interfaces = {str(e.get("name") or "").split(".", 1)[0] for e in sensor.findall("state_interface")}
    params = {str(e.get("name")): (e.text or "").strip() for e in sensor.findall("param")}
    kind: SensorKind
    if interfaces and interfaces <= {"force", "torque"}:
        kind = "force_torque"
    elif interfaces and interfaces <= {"orientation", "angular_velocity", "linear_acceleration"}:
        kind = "imu"
    else:
        log.debug("ros2_control sensor %r (interfaces %s) is not one agentsdk reads; left out", name,
                  sorted(interfaces))
        return None
    link = params.get("frame_id") or params.get("sensor_frame") or name
    if link not in links:
        log.warning("ros2_control sensor %r: frame %r is not a link of the robot; left out", name, link)
        return None
    return SensorSpec(name=name, kind=kind, link=link, source="ros2_control")


# --------------------------------------------------------------------------- robot.yaml
def _yaml_sensors(config: RobotConfig, description: RobotDescription) -> list[SensorSpec]:
    entries: Sequence[Any] = getattr(config, "sensors", ())
    if not entries:
        return []
    from ..config import validation_problems

    links = set(description.links)
    joints = {j.name: j for j in description.all_joints}
    where = f"{config.label}: sensors"
    specs: list[SensorSpec] = []
    problems: list[str] = []
    seen: set[str] = set()
    for k, raw in enumerate(entries):
        try:
            entry = SensorYaml.model_validate(raw)
        except ValidationError as exc:
            problems.extend(f"{where}[{k}].{line}" for line in validation_problems(exc, SensorYaml))
            continue
        label = f"{where}[{k}] ({entry.name!r})"
        if entry.name in seen:
            problems.append(f"{label}: the name is used twice")
            continue
        seen.add(entry.name)
        link, joint = entry.link, entry.joint
        if joint is not None and joint not in joints:
            problems.append(f"{label}: unknown joint {joint!r}; the robot's joints are: {', '.join(joints)}")
            continue
        if link is not None and link not in links:
            problems.append(f"{label}: unknown link {link!r}; the robot's links are: {', '.join(description.links)}")
            continue
        if entry.type in JOINT_KINDS or entry.type == "temperature":
            if joint is None:
                problems.append(f"{label}: a {entry.type} sensor needs a joint")
                continue
        if link is None:
            if joint is None:
                problems.append(f"{label}: give the link (or the joint) the {entry.type} sensor is attached to")
                continue
            link = joints[joint].child
        if entry.ray is not None and entry.ray.max_angle < entry.ray.min_angle:
            problems.append(f"{label}: ray.max_angle is below ray.min_angle")
            continue
        limits = SensorLimits(entry.max_force, entry.max_torque, entry.max_tilt, entry.stop_category)
        bad = _limits_problem(entry.type, limits)
        if bad:
            problems.append(f"{label}: {bad}")
            continue
        camera = None
        if entry.type == "camera":
            c = entry.camera if entry.camera is not None else None
            camera = CameraSpec(**c.model_dump()) if c is not None else CameraSpec()
        ray = None
        if entry.type in ("lidar", "rangefinder"):
            ray = RaySpec(**entry.ray.model_dump()) if entry.ray is not None else RaySpec()
        specs.append(SensorSpec(
            name=entry.name, kind=entry.type, link=link, joint=joint, xyz=entry.xyz,
            quat=_quat_rpy(*entry.rpy), rate=entry.rate, noise=entry.noise, bias=entry.bias,
            latency=entry.latency, source="robot.yaml", camera=camera, ray=ray, limits=limits,
        ))
    if problems:
        raise ConfigurationError("\n".join(problems))
    return specs


def _limits_problem(kind: str, limits: SensorLimits) -> str:
    if limits.max_force is not None and kind not in ("force_torque", "force", "contact"):
        return f"max_force applies to force_torque, force and contact sensors, not {kind}"
    if limits.max_torque is not None and kind not in ("force_torque", "torque"):
        return f"max_torque applies to force_torque and torque sensors, not {kind}"
    if limits.max_tilt is not None and kind not in ("imu", "orientation"):
        return f"max_tilt applies to imu and orientation sensors, not {kind}"
    return ""
