"""What to do when a CAN bus cannot be opened: one hint per cause, shared by the backend and the emulator."""

from __future__ import annotations

import errno

__all__ = ["bus_open_hint"]


def bus_open_hint(interface: str, channel: str, exc: BaseException) -> str:
    """A sentence saying why ``interface:channel`` did not open and what to do ("" when there is nothing to add)."""
    if interface != "socketcan":
        return ""
    code = getattr(exc, "errno", None)
    if code is None and isinstance(exc.__cause__, OSError):
        code = exc.__cause__.errno
    vcan = ("to try without CAN hardware, run inside a user-mode Linux kernel with a virtual bus: "
            "`agentsdk vcan -- agentsdk ...` (channel vcan0)")
    if code == errno.EAFNOSUPPORT:
        return f"this kernel has no SocketCAN (CAN support is missing, e.g. in a container); {vcan}"
    if code in (errno.ENODEV, errno.ENXIO):
        return (f"there is no CAN interface {channel!r}: create a virtual one with "
                f"`sudo ip link add dev {channel} type vcan && sudo ip link set up {channel}`, or {vcan}")
    if code in (errno.EPERM, errno.EACCES):
        return f"not allowed to open {channel!r}: run as root or with CAP_NET_RAW"
    return ""
