"""What a backend is built from, as one immutable value: :class:`BackendSpec`.

The joints with their limits after robot.yaml overrides, the validated options, the start pose,
the gravity-compensation and inverse-dynamics flags of the servo law, the control period and the
time model. :meth:`BackendSpec.build` derives it from the robot's configuration and description;
the :class:`~agentsdk.backend.Backend` base class adopts it (``backend.spec``), so a backend reads
ready values instead of computing them in its constructor, and the derivation is one function that
can be called (and tested) without a backend.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .types import FloatArray, JointInfo

if TYPE_CHECKING:
    from .config import RobotConfig
    from .description import RobotDescription
    from .description.start import StartPose

__all__ = ["BackendSpec"]

log = logging.getLogger("agentsdk")


def _readonly(values: Any) -> FloatArray:
    arr = np.array(values, dtype=np.float64)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class BackendSpec:
    """The ready values a backend is built from (every array read-only, in ``joints`` order)."""

    #: the validated robot.yaml (or defaults for a bare description)
    config: RobotConfig
    #: the loaded robot description
    description: RobotDescription
    #: actuated joints in order, with limits after robot.yaml overrides
    joints: tuple[JointInfo, ...]
    #: True when paced to the wall clock, False in lockstep
    realtime: bool
    #: the validated backend options (an instance of the backend's ``options_model``, or None)
    options: Any
    #: control period (s)
    period: float
    #: joint names in ``joints`` order
    names: tuple[str, ...]
    #: position limits, velocity and effort limits per joint
    lower: FloatArray
    upper: FloatArray
    max_velocity: FloatArray
    max_effort: FloatArray
    #: the start pose and where each joint's value came from (:mod:`agentsdk.description.start`)
    start_pose: StartPose
    #: where the joints start: robot.yaml ``initial_positions``, an SRDF group state, the model's
    #: home pose, else 0 -- always inside the limits
    initial_positions: FloatArray
    #: per joint: the servo law adds the model's gravity torque (robot.yaml ``gravity_compensation``,
    #: a backend option ``gravity_compensation`` overrides it for every joint)
    gravity_compensation: np.ndarray
    #: the servo law adds the inverse dynamics of the desired motion (robot.yaml ``inverse_dynamics``,
    #: or the backend option of that name)
    inverse_dynamics: bool

    @classmethod
    def build(
        cls,
        config: RobotConfig,
        description: RobotDescription,
        joints: tuple[JointInfo, ...],
        options: Any,
        *,
        realtime: bool,
    ) -> BackendSpec:
        """Derive the spec from the configuration, the description, the joints and the validated options.

        Logs the start pose's warning (a joint whose start value had to be moved into its limits).
        """
        from .description.start import start_pose

        start = start_pose(description, config, joints)
        warning = start.warning(config.name or description.name)
        if warning:
            log.warning("%s", warning)
        gc = np.array([config.gravity_compensation_for(j.name) for j in joints], dtype=bool)
        override = getattr(options, "gravity_compensation", None)  # a backend option may switch it
        if override is not None:
            gc[:] = bool(override)
        gc.flags.writeable = False
        id_override = getattr(options, "inverse_dynamics", None)  # connect(..., inverse_dynamics=...)
        return cls(
            config=config,
            description=description,
            joints=joints,
            realtime=bool(realtime),
            options=options,
            period=config.control_period,
            names=tuple(j.name for j in joints),
            lower=_readonly([j.lower for j in joints]),
            upper=_readonly([j.upper for j in joints]),
            max_velocity=_readonly([j.max_velocity for j in joints]),
            max_effort=_readonly([j.max_effort for j in joints]),
            start_pose=start,
            initial_positions=_readonly([start.positions[j.name] for j in joints]),
            gravity_compensation=gc,
            inverse_dynamics=bool(config.inverse_dynamics if id_override is None else id_override),
        )
