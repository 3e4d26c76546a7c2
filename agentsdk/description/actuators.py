"""The position servos an MJCF declares for its joints: the robot author's gains.

A MuJoCo position servo (``<position kp=... kv=... | dampratio=...>``, or a ``<general>``
actuator written in the same form) acting on one joint through a joint transmission
produces ``force = kp (ctrl - gear q) - kv gear q_dot`` and a joint torque ``gear force``,
so on the joint it is the servo law ``Kp (q* - q) - Kd q_dot`` with::

    Kp = kp gear**2      Kd = kv gear**2      (q* = ctrl / gear)

Read from the compiled model: MuJoCo has turned a ``dampratio`` into ``kv`` at compile time.
What counts as a position servo: a fixed gain ``kp > 0``, an affine bias ``[0, -kp, -kv]``
(``kv >= 0``), no activation dynamics (an ``intvelocity`` integrator is not one), a joint
transmission. A joint driven by motors (torque actuators), velocity servos or nothing has
no declared servo; a joint with several position servos gets their sum (they act together).
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["declared_servo_gains"]


def declared_servo_gains(model: Any) -> dict[int, tuple[float, float]]:
    """``{joint id: (Kp, Kd)}`` of the position servos in a compiled ``mujoco.MjModel`` (see the module doc)."""
    import mujoco

    out: dict[int, tuple[float, float]] = {}
    for a in range(model.nu):
        if int(model.actuator_trntype[a]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            continue
        if int(model.actuator_gaintype[a]) != int(mujoco.mjtGain.mjGAIN_FIXED):
            continue
        if int(model.actuator_biastype[a]) != int(mujoco.mjtBias.mjBIAS_AFFINE):
            continue
        if int(model.actuator_dyntype[a]) != int(mujoco.mjtDyn.mjDYN_NONE):
            continue
        kp = float(model.actuator_gainprm[a, 0])
        b0, b1, b2 = (float(v) for v in model.actuator_biasprm[a, :3])
        kv = -b2
        if not (kp > 0.0 and math.isfinite(kp) and b0 == 0.0 and math.isclose(-b1, kp, rel_tol=1e-9)):
            continue
        if not (kv >= 0.0 and math.isfinite(kv)):
            continue
        gear2 = float(model.actuator_gear[a, 0]) ** 2
        jid = int(model.actuator_trnid[a, 0])
        p, d = out.get(jid, (0.0, 0.0))
        out[jid] = (p + kp * gear2, d + kv * gear2)
    return out
