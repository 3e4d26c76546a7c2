"""Joint Coulomb friction (MJCF ``frictionloss``, URDF ``<dynamics friction>``) in the implicit PyBullet step.

The step solves ``(M + h D) qacc = rhs + F`` for one physics step ``h``: ``F`` is the joints' friction
torque, each within +-its friction. The joints that can stop this step stop (their friction holds
them) and the others slide with their full friction against their motion. Which joint sticks is found
with the coupled matrix: a per-joint ("decoupled") estimate overshoots when two joints move a light
link together, e.g. xArm7's joint1 and joint3 whose axes line up at its home pose, where turning both
the opposite way moves only link2: the estimate reverses that motion a little more each step and the
arm slips until friction catches it (5 mrad on xArm7's wrist, 12 mrad on its gripper links).
"""

from __future__ import annotations

import numpy as np

__all__ = ["friction_torque"]


def friction_torque(a: np.ndarray, rhs: np.ndarray, v: np.ndarray, h: float, friction: np.ndarray) -> np.ndarray:
    """The friction torque ``F`` (``|F| <= friction``) of one implicit step ``a qacc = rhs + F``.

    With ``W = a / h`` the new velocity solves ``W v' = W v + rhs + F``. Sticking joints ``T`` have
    ``v'_T = 0``, sliding joints ``S`` feel ``F_S = -friction_S sign(v'_S)``: an active set, started
    from "every joint with friction sticks", moves a joint to ``S`` when holding it takes more than its
    friction and back to ``T`` when its friction would reverse it; frictionless joints always slide.
    """
    n = v.shape[0]
    w = a / h
    b: np.ndarray = w @ v + rhs  # F = -b stops every joint
    force: np.ndarray = np.clip(-b, -friction, friction)
    sliding = (friction <= 0.0) | (np.abs(b) > friction)
    if not sliding.any():
        return force  # every joint holds: the exact torque that stops them
    for _ in range(2 * n + 2):
        s = np.flatnonzero(sliding)
        t = np.flatnonzero(~sliding)
        v_s = np.linalg.solve(w[np.ix_(s, s)], b[s] + force[s]) if s.size else np.zeros(0)
        hold = w[np.ix_(t, s)] @ v_s - b[t]
        changed = False
        over = np.abs(hold) > friction[t] * (1.0 + 1e-12)
        if over.any():  # holding takes more than the friction: those joints slide
            idx = t[over]
            sliding[idx] = True
            force[idx] = np.clip(hold[over], -friction[idx], friction[idx])
            changed = True
        reverse = (v_s * force[s] > 0.0) & (friction[s] > 0.0)
        if reverse.any() and not changed:  # friction would drive the joint: it sticks
            sliding[s[reverse]] = False
            changed = True
        if not changed:
            force[t] = hold
            return force
    return _descend(w, b, friction)


def _descend(w: np.ndarray, b: np.ndarray, friction: np.ndarray, sweeps: int = 200) -> np.ndarray:
    """The same torque by coordinate descent, when the active set cycles (rare: strongly coupled joints).

    ``v'`` minimizes ``v'^T W v' / 2 - b^T v' + sum friction |v'|`` (convex: ``W`` is positive definite);
    each coordinate's exact minimum is a soft threshold, and every sweep lowers the objective.
    """
    vn = np.zeros_like(b)
    diag = np.diag(w)
    for _ in range(sweeps):
        largest = 0.0
        for i in range(b.shape[0]):
            r = b[i] - float(w[i] @ vn) + diag[i] * vn[i]
            new = np.sign(r) * max(abs(r) - friction[i], 0.0) / diag[i]
            largest = max(largest, abs(new - vn[i]))
            vn[i] = new
        if largest <= 1e-12 * (1.0 + float(np.abs(vn).max())):
            break
    force: np.ndarray = np.clip(w @ vn - b, -friction, friction)
    return force
