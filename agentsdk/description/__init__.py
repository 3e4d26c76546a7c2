"""Robot descriptions: URDF, xacro and MJCF files loaded into an immutable :class:`RobotDescription`.

``load_description`` expands xacro (``xacro.process_file``, in a sandboxed
worker process: :mod:`agentsdk.description.xacro_sandbox`), parses URDF by
ROS's urdfdom rules (errors name the file, the line for plain URDF files, and
the link or joint), resolves every mesh to an absolute filesystem path, and
repairs - visibly, once - what the simulators cannot take, so that MuJoCo
and PyBullet get the same masses, limits and geometry (see
:mod:`agentsdk.description.urdf` and :mod:`agentsdk.description.inertia`).
MJCF models (MuJoCo Menagerie style) are read through MuJoCo itself
(:mod:`agentsdk.description.mjcf`).

Mesh and ``$(find pkg)`` resolution follows ROS conventions
(:mod:`agentsdk.description.packages`); a robot file is data: the files it
reaches stay inside its package roots unless it is loaded ``trusted``. The self-collision model both
simulators use is decided once from the description
(:mod:`agentsdk.description.collision`).

``resolve_robot`` turns a robot name from the shipped ``robots/`` directory,
a ``robot.yaml``, or a bare description file into a validated
``(RobotConfig, RobotDescription)`` pair; ``apply_overrides`` merges
robot.yaml ``joint_limits`` into the description's limits.
"""

from __future__ import annotations

from .loader import is_mjcf, load_description, repair_report
from .model import (
    DEFAULT_VELOCITY,
    Geometry,
    Inertial,
    JointRecord,
    LinkRecord,
    Mimic,
    Repair,
    RobotDescription,
)
from .packages import PACKAGE_PATH_ENV_VARS, find_package, package_search_path
from .robot_yaml import apply_overrides, check_config, list_robots, resolve_robot

__all__ = [
    "DEFAULT_VELOCITY",
    "PACKAGE_PATH_ENV_VARS",
    "Geometry",
    "Inertial",
    "JointRecord",
    "LinkRecord",
    "Mimic",
    "Repair",
    "RobotDescription",
    "apply_overrides",
    "check_config",
    "find_package",
    "is_mjcf",
    "list_robots",
    "load_description",
    "package_search_path",
    "repair_report",
    "resolve_robot",
]
