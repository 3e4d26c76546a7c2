"""Robot descriptions shipped with agentsdk.

Each robot lives in its own directory holding a ``robot.yaml`` (schema:
:class:`agentsdk.config.RobotConfig`) and its xacro/URDF files:

* ``arm3`` - the classic 3-joint arm (yaw, pitch, wrist roll) on a fixed base
* ``humanoid`` - a fixed-base humanoid with 15 actuated joints
* ``mit_leg`` - a 3-joint leg on a test stand, driven by MIT-protocol CAN motors

``common/`` holds shared xacro macros (inertials of solid primitives).
Use ``agentsdk.description.list_robots()`` / ``resolve_robot(name)``.
"""

from pathlib import Path

__all__ = ["ROBOTS_DIR"]

#: the directory holding one sub-directory per robot
ROBOTS_DIR: Path = Path(__file__).resolve().parent
