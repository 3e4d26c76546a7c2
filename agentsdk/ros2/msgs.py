"""ROS 2 message, service and action types as DDS (``cyclonedds``) types, without ROS.

Each class is a ``@final`` IDL struct with the DDS type name ROS 2 uses on the wire
(``sensor_msgs/msg/JointState`` is ``sensor_msgs::msg::dds_::JointState_``), so its
XCDR1 little-endian serialisation is exactly what a ROS 2 node sends and expects
(checked byte for byte against ``rosbags`` in ``tests/test_ros2_msgs.py``).

Field layouts follow ROS 2 Humble (``control_msgs`` 4.x: ``FollowJointTrajectory``
feedback and ``JointTrajectoryControllerState`` changed shape in later releases).
Services (``*_Request_`` / ``*_Response_``) are the message part only: on the wire,
``rmw_cyclonedds`` prepends a :class:`RequestHeader` (see :mod:`agentsdk.ros2.wire`).
"""

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cyclonedds.idl.annotations as annotate
from cyclonedds.idl import IdlStruct

if TYPE_CHECKING:
    # what the fields hold in Python (cyclonedds' IDL type markers are not types mypy understands)
    from typing import TypeAlias

    float64: TypeAlias = float
    int8: TypeAlias = int
    int32: TypeAlias = int
    int64: TypeAlias = int
    uint8: TypeAlias = int
    uint16: TypeAlias = int
    uint32: TypeAlias = int
    uint64: TypeAlias = int
    sequence = list
    Octets16: TypeAlias = bytes
    Octets24: TypeAlias = bytes
else:
    from cyclonedds.idl.types import array, float64, int8, int32, int64, sequence, uint8, uint16, uint32, uint64

    Octets16 = array[uint8, 16]
    Octets24 = array[uint8, 24]

__all__ = [
    "UUID",
    "CancelGoal_Request",
    "CancelGoal_Response",
    "Clock",
    "DiagnosticArray",
    "DiagnosticStatus",
    "Duration",
    "FollowJointTrajectory_Feedback",
    "FollowJointTrajectory_FeedbackMessage",
    "FollowJointTrajectory_GetResult_Request",
    "FollowJointTrajectory_GetResult_Response",
    "FollowJointTrajectory_Goal",
    "FollowJointTrajectory_Result",
    "FollowJointTrajectory_SendGoal_Request",
    "FollowJointTrajectory_SendGoal_Response",
    "Gid",
    "GoalInfo",
    "GoalStatus",
    "GoalStatusArray",
    "Header",
    "JointComponentTolerance",
    "JointState",
    "JointTolerance",
    "JointTrajectory",
    "JointTrajectoryControllerState",
    "JointTrajectoryPoint",
    "KeyValue",
    "MultiDOFJointTrajectory",
    "MultiDOFJointTrajectoryPoint",
    "NodeEntitiesInfo",
    "ParticipantEntitiesInfo",
    "Quaternion",
    "RequestHeader",
    "String",
    "TFMessage",
    "Time",
    "Transform",
    "TransformStamped",
    "Trigger_Request",
    "Trigger_Response",
    "Twist",
    "Vector3",
]


def _dds(ros_name: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (the DDS type name ROS 2 uses)."""
    pkg, kind, name = ros_name.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


# ------------------------------------------------------------------ builtin_interfaces, std_msgs
@dataclass
@annotate.final
class Time(IdlStruct, typename=_dds("builtin_interfaces/msg/Time")):
    """``builtin_interfaces/msg/Time``: seconds and nanoseconds."""

    sec: int32 = 0
    nanosec: uint32 = 0

    @classmethod
    def from_seconds(cls, t: float) -> "Time":
        """The Time of ``t`` seconds, rounded to the nanosecond."""
        ns = round(t * 1e9)
        return cls(ns // 1_000_000_000, ns % 1_000_000_000)

    def to_seconds(self) -> float:
        """This time in seconds."""
        return self.sec + self.nanosec * 1e-9


@dataclass
@annotate.final
class Duration(IdlStruct, typename=_dds("builtin_interfaces/msg/Duration")):
    """``builtin_interfaces/msg/Duration``."""

    sec: int32 = 0
    nanosec: uint32 = 0

    @classmethod
    def from_seconds(cls, t: float) -> "Duration":
        """The Duration of ``t`` seconds, rounded to the nanosecond."""
        ns = round(t * 1e9)
        return cls(ns // 1_000_000_000, ns % 1_000_000_000)

    def to_seconds(self) -> float:
        """This duration in seconds."""
        return self.sec + self.nanosec * 1e-9


@dataclass
@annotate.final
class Header(IdlStruct, typename=_dds("std_msgs/msg/Header")):
    """``std_msgs/msg/Header``."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
@annotate.final
class String(IdlStruct, typename=_dds("std_msgs/msg/String")):
    """``std_msgs/msg/String``."""

    data: str = ""


@dataclass
@annotate.final
class Clock(IdlStruct, typename=_dds("rosgraph_msgs/msg/Clock")):
    """``rosgraph_msgs/msg/Clock``: the simulated time ``use_sim_time`` nodes follow."""

    clock: Time = field(default_factory=Time)


# ------------------------------------------------------------------ sensor_msgs, geometry_msgs, tf2_msgs
@dataclass
@annotate.final
class JointState(IdlStruct, typename=_dds("sensor_msgs/msg/JointState")):
    """``sensor_msgs/msg/JointState``."""

    header: Header = field(default_factory=Header)
    name: sequence[str] = field(default_factory=list)
    position: sequence[float64] = field(default_factory=list)
    velocity: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)


@dataclass
@annotate.final
class Vector3(IdlStruct, typename=_dds("geometry_msgs/msg/Vector3")):
    """``geometry_msgs/msg/Vector3``."""

    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
@annotate.final
class Quaternion(IdlStruct, typename=_dds("geometry_msgs/msg/Quaternion")):
    """``geometry_msgs/msg/Quaternion`` (x, y, z, w; identity by default)."""

    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
@annotate.final
class Transform(IdlStruct, typename=_dds("geometry_msgs/msg/Transform")):
    """``geometry_msgs/msg/Transform``."""

    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
@annotate.final
class TransformStamped(IdlStruct, typename=_dds("geometry_msgs/msg/TransformStamped")):
    """``geometry_msgs/msg/TransformStamped``: ``child_frame_id`` in ``header.frame_id``."""

    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
@annotate.final
class Twist(IdlStruct, typename=_dds("geometry_msgs/msg/Twist")):
    """``geometry_msgs/msg/Twist``."""

    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
@annotate.final
class TFMessage(IdlStruct, typename=_dds("tf2_msgs/msg/TFMessage")):
    """``tf2_msgs/msg/TFMessage``: what ``/tf`` and ``/tf_static`` carry."""

    transforms: sequence[TransformStamped] = field(default_factory=list)


# ------------------------------------------------------------------ trajectory_msgs
@dataclass
@annotate.final
class JointTrajectoryPoint(IdlStruct, typename=_dds("trajectory_msgs/msg/JointTrajectoryPoint")):
    """``trajectory_msgs/msg/JointTrajectoryPoint``."""

    positions: sequence[float64] = field(default_factory=list)
    velocities: sequence[float64] = field(default_factory=list)
    accelerations: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)
    time_from_start: Duration = field(default_factory=Duration)


@dataclass
@annotate.final
class JointTrajectory(IdlStruct, typename=_dds("trajectory_msgs/msg/JointTrajectory")):
    """``trajectory_msgs/msg/JointTrajectory``."""

    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    points: sequence[JointTrajectoryPoint] = field(default_factory=list)


@dataclass
@annotate.final
class MultiDOFJointTrajectoryPoint(IdlStruct, typename=_dds("trajectory_msgs/msg/MultiDOFJointTrajectoryPoint")):
    """``trajectory_msgs/msg/MultiDOFJointTrajectoryPoint``."""

    transforms: sequence[Transform] = field(default_factory=list)
    velocities: sequence[Twist] = field(default_factory=list)
    accelerations: sequence[Twist] = field(default_factory=list)
    time_from_start: Duration = field(default_factory=Duration)


@dataclass
@annotate.final
class MultiDOFJointTrajectory(IdlStruct, typename=_dds("trajectory_msgs/msg/MultiDOFJointTrajectory")):
    """``trajectory_msgs/msg/MultiDOFJointTrajectory``."""

    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    points: sequence[MultiDOFJointTrajectoryPoint] = field(default_factory=list)


# ------------------------------------------------------------------ diagnostic_msgs
@dataclass
@annotate.final
class KeyValue(IdlStruct, typename=_dds("diagnostic_msgs/msg/KeyValue")):
    """``diagnostic_msgs/msg/KeyValue``."""

    key: str = ""
    value: str = ""


@dataclass
@annotate.final
class DiagnosticStatus(IdlStruct, typename=_dds("diagnostic_msgs/msg/DiagnosticStatus")):
    """``diagnostic_msgs/msg/DiagnosticStatus`` (level OK 0, WARN 1, ERROR 2, STALE 3)."""

    level: uint8 = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: sequence[KeyValue] = field(default_factory=list)


@dataclass
@annotate.final
class DiagnosticArray(IdlStruct, typename=_dds("diagnostic_msgs/msg/DiagnosticArray")):
    """``diagnostic_msgs/msg/DiagnosticArray``."""

    header: Header = field(default_factory=Header)
    status: sequence[DiagnosticStatus] = field(default_factory=list)


# ------------------------------------------------------------------ std_srvs
@dataclass
@annotate.final
class Trigger_Request(IdlStruct, typename=_dds("std_srvs/srv/Trigger_Request")):
    """``std_srvs/srv/Trigger`` request (empty: ROS IDL adds one placeholder byte)."""

    structure_needs_at_least_one_member: uint8 = 0


@dataclass
@annotate.final
class Trigger_Response(IdlStruct, typename=_dds("std_srvs/srv/Trigger_Response")):
    """``std_srvs/srv/Trigger`` response."""

    success: bool = False
    message: str = ""


# ------------------------------------------------------------------ unique_identifier_msgs, action_msgs
@dataclass
@annotate.final
class UUID(IdlStruct, typename=_dds("unique_identifier_msgs/msg/UUID")):
    """``unique_identifier_msgs/msg/UUID``: 16 bytes."""

    uuid: Octets16 = field(default_factory=lambda: bytes(16))


@dataclass
@annotate.final
class GoalInfo(IdlStruct, typename=_dds("action_msgs/msg/GoalInfo")):
    """``action_msgs/msg/GoalInfo``."""

    goal_id: UUID = field(default_factory=UUID)
    stamp: Time = field(default_factory=Time)


@dataclass
@annotate.final
class GoalStatus(IdlStruct, typename=_dds("action_msgs/msg/GoalStatus")):
    """``action_msgs/msg/GoalStatus`` (status codes in :mod:`agentsdk.ros2.action`)."""

    goal_info: GoalInfo = field(default_factory=GoalInfo)
    status: int8 = 0


@dataclass
@annotate.final
class GoalStatusArray(IdlStruct, typename=_dds("action_msgs/msg/GoalStatusArray")):
    """``action_msgs/msg/GoalStatusArray``: what an action's ``_action/status`` topic carries."""

    status_list: sequence[GoalStatus] = field(default_factory=list)


@dataclass
@annotate.final
class CancelGoal_Request(IdlStruct, typename=_dds("action_msgs/srv/CancelGoal_Request")):
    """``action_msgs/srv/CancelGoal`` request (a zero goal id and stamp cancel every goal)."""

    goal_info: GoalInfo = field(default_factory=GoalInfo)


@dataclass
@annotate.final
class CancelGoal_Response(IdlStruct, typename=_dds("action_msgs/srv/CancelGoal_Response")):
    """``action_msgs/srv/CancelGoal`` response (return codes NONE 0, REJECTED 1, UNKNOWN_GOAL_ID 2, TERMINATED 3)."""

    return_code: int8 = 0
    goals_canceling: sequence[GoalInfo] = field(default_factory=list)


# ------------------------------------------------------------------ control_msgs (Humble)
@dataclass
@annotate.final
class JointTolerance(IdlStruct, typename=_dds("control_msgs/msg/JointTolerance")):
    """``control_msgs/msg/JointTolerance`` (0: default, -1: not checked)."""

    name: str = ""
    position: float64 = 0.0
    velocity: float64 = 0.0
    acceleration: float64 = 0.0


@dataclass
@annotate.final
class JointComponentTolerance(IdlStruct, typename=_dds("control_msgs/msg/JointComponentTolerance")):
    """``control_msgs/msg/JointComponentTolerance`` (multi-DOF joints; not used by agentsdk)."""

    joint_name: str = ""
    component: uint16 = 0
    position: float64 = 0.0
    velocity: float64 = 0.0
    acceleration: float64 = 0.0


@dataclass
@annotate.final
class JointTrajectoryControllerState(IdlStruct, typename=_dds("control_msgs/msg/JointTrajectoryControllerState")):
    """``control_msgs/msg/JointTrajectoryControllerState`` as in Humble (``desired``/``actual`` kept)."""

    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    reference: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    feedback: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    error: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    output: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    desired: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    actual: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    multi_dof_joint_names: sequence[str] = field(default_factory=list)
    multi_dof_reference: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_feedback: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_error: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_output: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_desired: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_actual: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)


@dataclass
@annotate.final
class FollowJointTrajectory_Goal(IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_Goal")):
    """``control_msgs/action/FollowJointTrajectory`` goal."""

    trajectory: JointTrajectory = field(default_factory=JointTrajectory)
    multi_dof_trajectory: MultiDOFJointTrajectory = field(default_factory=MultiDOFJointTrajectory)
    path_tolerance: sequence[JointTolerance] = field(default_factory=list)
    component_path_tolerance: sequence[JointComponentTolerance] = field(default_factory=list)
    goal_tolerance: sequence[JointTolerance] = field(default_factory=list)
    component_goal_tolerance: sequence[JointComponentTolerance] = field(default_factory=list)
    goal_time_tolerance: Duration = field(default_factory=Duration)


@dataclass
@annotate.final
class FollowJointTrajectory_Result(IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_Result")):
    """``control_msgs/action/FollowJointTrajectory`` result (``error_code``: see :class:`agentsdk.ResultCode`)."""

    error_code: int32 = 0
    error_string: str = ""


@dataclass
@annotate.final
class FollowJointTrajectory_Feedback(IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_Feedback")):
    """``control_msgs/action/FollowJointTrajectory`` feedback (Humble layout)."""

    header: Header = field(default_factory=Header)
    joint_names: sequence[str] = field(default_factory=list)
    desired: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    actual: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    error: JointTrajectoryPoint = field(default_factory=JointTrajectoryPoint)
    multi_dof_joint_names: sequence[str] = field(default_factory=list)
    multi_dof_desired: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_actual: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)
    multi_dof_error: MultiDOFJointTrajectoryPoint = field(default_factory=MultiDOFJointTrajectoryPoint)


@dataclass
@annotate.final
class FollowJointTrajectory_SendGoal_Request(
    IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_SendGoal_Request")
):
    """The action's ``send_goal`` service request."""

    goal_id: UUID = field(default_factory=UUID)
    goal: FollowJointTrajectory_Goal = field(default_factory=FollowJointTrajectory_Goal)


@dataclass
@annotate.final
class FollowJointTrajectory_SendGoal_Response(
    IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_SendGoal_Response")
):
    """The action's ``send_goal`` service response."""

    accepted: bool = False
    stamp: Time = field(default_factory=Time)


@dataclass
@annotate.final
class FollowJointTrajectory_GetResult_Request(
    IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_GetResult_Request")
):
    """The action's ``get_result`` service request."""

    goal_id: UUID = field(default_factory=UUID)


@dataclass
@annotate.final
class FollowJointTrajectory_GetResult_Response(
    IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_GetResult_Response")
):
    """The action's ``get_result`` service response (``status``: a GoalStatus code)."""

    status: int8 = 0
    result: FollowJointTrajectory_Result = field(default_factory=FollowJointTrajectory_Result)


@dataclass
@annotate.final
class FollowJointTrajectory_FeedbackMessage(
    IdlStruct, typename=_dds("control_msgs/action/FollowJointTrajectory_FeedbackMessage")
):
    """What the action's ``_action/feedback`` topic carries."""

    goal_id: UUID = field(default_factory=UUID)
    feedback: FollowJointTrajectory_Feedback = field(default_factory=FollowJointTrajectory_Feedback)


# ------------------------------------------------------------------ rmw_dds_common (Humble): node discovery
@dataclass
@annotate.final
class Gid(IdlStruct, typename=_dds("rmw_dds_common/msg/Gid")):
    """``rmw_dds_common/msg/Gid`` (Humble: 24 bytes): a DDS GUID's 16 bytes, zero padded."""

    data: Octets24 = field(default_factory=lambda: bytes(24))


@dataclass
@annotate.final
class NodeEntitiesInfo(IdlStruct, typename=_dds("rmw_dds_common/msg/NodeEntitiesInfo")):
    """``rmw_dds_common/msg/NodeEntitiesInfo``: one node and its readers' and writers' ids."""

    node_namespace: str = ""
    node_name: str = ""
    reader_gid_seq: sequence[Gid] = field(default_factory=list)
    writer_gid_seq: sequence[Gid] = field(default_factory=list)


@dataclass
@annotate.final
class ParticipantEntitiesInfo(IdlStruct, typename=_dds("rmw_dds_common/msg/ParticipantEntitiesInfo")):
    """``rmw_dds_common/msg/ParticipantEntitiesInfo``: what ``ros_discovery_info`` carries (``ros2 node list``)."""

    gid: Gid = field(default_factory=Gid)
    node_entities_info_seq: sequence[NodeEntitiesInfo] = field(default_factory=list)


# ------------------------------------------------------------------ rmw_cyclonedds request header
@dataclass
@annotate.final
class RequestHeader(IdlStruct, typename="agentsdk::ros2::RequestHeader"):
    """The request identity ``rmw_cyclonedds`` puts before every request and reply sample.

    ``guid``: the first 8 bytes of the client's request writer GUID as a little-endian
    integer (unique per client in the process's participant); ``seq``: the client's request
    sequence number. A reply repeats the request's header.
    """

    guid: uint64 = 0
    seq: int64 = 0
