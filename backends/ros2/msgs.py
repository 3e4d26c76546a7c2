"""The ROS messages only the ``ros2`` backend sends: ``std_msgs/Float64MultiArray`` (forward_command_controller)."""


from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cyclonedds.idl.annotations as annotate
from cyclonedds.idl import IdlStruct

if TYPE_CHECKING:  # what the fields hold in Python (as in agentsdk.ros2.msgs)
    from typing import TypeAlias

    float64: TypeAlias = float
    uint32: TypeAlias = int
    sequence = list
else:
    from cyclonedds.idl.types import float64, sequence, uint32

__all__ = ["Float64MultiArray", "MultiArrayDimension", "MultiArrayLayout"]


@dataclass
@annotate.final
class MultiArrayDimension(IdlStruct, typename="std_msgs::msg::dds_::MultiArrayDimension_"):
    """``std_msgs/msg/MultiArrayDimension``."""

    label: str = ""
    size: uint32 = 0
    stride: uint32 = 0


@dataclass
@annotate.final
class MultiArrayLayout(IdlStruct, typename="std_msgs::msg::dds_::MultiArrayLayout_"):
    """``std_msgs/msg/MultiArrayLayout``."""

    dim: sequence[MultiArrayDimension] = field(default_factory=list)
    data_offset: uint32 = 0


@dataclass
@annotate.final
class Float64MultiArray(IdlStruct, typename="std_msgs::msg::dds_::Float64MultiArray_"):
    """``std_msgs/msg/Float64MultiArray``: what a forward_command_controller's ``commands`` topic takes."""

    layout: MultiArrayLayout = field(default_factory=MultiArrayLayout)
    data: sequence[float64] = field(default_factory=list)
