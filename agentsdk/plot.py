"""Plots of recorded runs: desired vs actual joint positions and the tracking error.

Uses matplotlib's object API with the Agg canvas (no pyplot, no GUI, no global
state), so it works headless and from any thread::

    from agentsdk.recording import read_recording
    from agentsdk.plot import plot_run

    fig = plot_run(read_recording("run.mcap"), "run.png")

One panel per joint (desired position from ``/joint_commands`` as a
sample-and-hold step, the commanded target before ramping dotted, the measured
position from ``/joint_states``), then one panel with the tracking error
(desired - actual) of every joint. Joints that are not position-servoed at a
time (velocity/effort mode, torque off) have no desired position there.
A recording with sensors adds one panel per sensor (``/sensors/<name>``): its
components against robot time, in SI units (an IMU: linear acceleration solid,
angular velocity dashed).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import numpy as np

from .backend import ModeCode
from .errors import ConfigurationError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from .recording import RunData
    from .recording._sensors import SensorSeries

__all__ = ["plot_run"]

_NS = 1e9


def plot_run(
    data: RunData,
    path: str | os.PathLike[str] | None = None,
    *,
    reference: RunData | None = None,
    title: str | None = None,
    dpi: int = 100,
) -> Figure:
    """Draw ``data`` (one panel per joint plus a tracking-error panel); save a PNG to ``path`` if given.

    ``reference`` (e.g. the original run when plotting a replay) is overlaid dashed.
    Returns the figure (``len(fig.axes) == len(data.names) + 1 + len(data.sensors)``).
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - matplotlib is a dependency
        raise ConfigurationError("plotting needs matplotlib: pip install matplotlib") from exc

    names = data.names
    n = len(names)
    if n == 0:
        raise ConfigurationError("nothing to plot: the run has no joints")
    t = data.state_time / _NS
    actual = data.position
    desired = data.desired_position()
    error = desired - actual

    sensors = list(data.sensors.values())
    rows = n + 1 + len(sensors)
    fig = Figure(figsize=(10.0, 1.9 * rows + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    if title is None:
        md = data.metadata
        robot = md.get("robot_name") or md.get("robot") or "robot"
        backend = md.get("backend", "?")
        mode = "real time" if md.get("realtime") == "true" else "lockstep"
        behavior = md.get("behavior")
        title = f"{robot} on {backend} ({mode})" + (f": {os.path.basename(behavior)}" if behavior else "")
    fig.suptitle(title)

    target = _target_at(data)
    for j, (ax, name) in enumerate(zip(axes[:n], names, strict=True)):
        ax.plot(t, desired[:, j], drawstyle="steps-pre", color="tab:orange", lw=1.2, label="desired (setpoint)")
        if target is not None and not np.allclose(target[:, j], desired[:, j], equal_nan=True):
            ax.plot(t, target[:, j], drawstyle="steps-pre", color="tab:gray", lw=0.8, ls=":", label="target")
        ax.plot(t, actual[:, j], color="tab:blue", lw=1.0, label="actual")
        if reference is not None and name in reference.names:
            k = reference.names.index(name)
            ax.plot(
                reference.state_time / _NS, reference.position[:, k], color="black", lw=0.8, ls="--", label="reference"
            )
        ax.set_ylabel(f"{name}\n[rad]")
        ax.grid(True, alpha=0.3)
        if j == 0:
            ax.legend(loc="upper right", fontsize="small", ncols=4)

    ax_err = axes[n]
    for j, name in enumerate(names):
        ax_err.plot(t, error[:, j], lw=1.0, label=name)
    ax_err.axhline(0.0, color="black", lw=0.5)
    ax_err.set_ylabel("tracking error\n(desired - actual) [rad]")
    ax_err.grid(True, alpha=0.3)
    ax_err.legend(loc="upper right", fontsize="small", ncols=min(n, 6))
    for ax, series in zip(axes[n + 1 :], sensors, strict=True):
        _sensor_panel(ax, series)
    axes[-1].set_xlabel("robot time [s]")
    if path is not None:
        try:
            fig.savefig(os.fspath(path), dpi=dpi)
        except OSError as exc:
            raise ConfigurationError(f"cannot write plot {path}: {exc.strerror or exc}") from exc
    return fig


#: per sensor kind: (column, label, dashed) of what its panel shows, and the y label's unit
_SENSOR_LINES: dict[str, tuple[list[tuple[int, str, bool]], str]] = {
    "imu": ([(7, "acc x", False), (8, "acc y", False), (9, "acc z", False), (4, "gyro x", True),
             (5, "gyro y", True), (6, "gyro z", True)], "m/s², rad/s"),
    "force_torque": ([(0, "Fx", False), (1, "Fy", False), (2, "Fz", False), (3, "Tx", True), (4, "Ty", True),
                      (5, "Tz", True)], "N, N·m"),
    "accelerometer": ([(0, "x", False), (1, "y", False), (2, "z", False)], "m/s²"),
    "gyro": ([(0, "x", False), (1, "y", False), (2, "z", False)], "rad/s"),
    "force": ([(0, "x", False), (1, "y", False), (2, "z", False)], "N"),
    "torque": ([(0, "x", False), (1, "y", False), (2, "z", False)], "N·m"),
    "orientation": ([(0, "x", False), (1, "y", False), (2, "z", False), (3, "w", False)], "quaternion"),
    "contact": ([(0, "normal force", False)], "N"),
    "rangefinder": ([(0, "range", False)], "m"),
    "temperature": ([(0, "temperature", False)], "°C"),
}


_JOINT_UNITS = {"joint_position": "rad or m", "joint_velocity": "rad/s or m/s", "joint_effort": "N·m or N"}


def _sensor_panel(ax: Any, series: SensorSeries) -> None:
    """One sensor's components against robot time (a lidar: its minimum range per scan)."""
    t = series.time / _NS
    v = series.values
    kind = series.type
    if kind == "lidar":  # the closest return of each scan (NaN: nothing in range)
        closest = np.min(np.where(np.isfinite(v), v, np.inf), axis=1, initial=np.inf)
        v = np.where(np.isfinite(closest), closest, np.nan)[:, None]
        lines, unit = [(0, "closest range", False)], "m"
    elif kind in _SENSOR_LINES:
        lines, unit = _SENSOR_LINES[kind]
    else:  # a joint sensor
        unit = _JOINT_UNITS.get(kind, "")
        lines = [(0, series.joint or "value", False)]
    for col, label, dashed in lines:
        ax.plot(t, v[:, col], drawstyle="steps-post", lw=1.0, ls="--" if dashed else "-", label=label)
    ax.set_ylabel(f"{series.name}\n{kind} [{unit}]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize="small", ncols=min(len(lines), 6))


def _target_at(data: RunData) -> np.ndarray | None:
    """The commanded position target (before ramping) behind every state, NaN outside position mode."""
    if not len(data.cmd_time):
        return None
    idx = data.command_index(data.state_time)
    ok = idx >= 0
    rows = idx[ok]
    out = np.full_like(data.position, np.nan)
    servo = (data.cmd_mode[rows] == ModeCode.POSITION) & data.cmd_enabled[rows]
    out[ok] = np.where(servo, data.cmd_target[rows], np.nan)
    return out
