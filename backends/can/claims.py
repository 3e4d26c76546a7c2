"""One controller per bus and per motor, within this process.

Two controllers streaming to one motor fight over it, and when one of them closes it
disables the motor under the other. :func:`claim` registers ``(interface, channel, motor
id)`` for an opening CAN backend and refuses, with :class:`~agentsdk.errors.BusClaimedError`,
ids another open backend of this process already holds; :meth:`Claim.release` (from the
backend's close, also after a failed open) gives them back. Other processes and other
devices on the wire are detected on the bus itself (see the backend's bus-conflict checks).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable

from agentsdk.errors import BusClaimedError

__all__ = ["Claim", "claim", "claimed"]

_lock = threading.Lock()
#: (interface, channel, motor id) -> the claim holding it
_held: dict[tuple[str, str, int], Claim] = {}


class Claim:
    """Motor ids on one bus channel held by one open backend; :meth:`release` is idempotent."""

    __slots__ = ("_keys", "channel", "ids", "interface", "owner")

    def __init__(self, interface: str, channel: str, ids: tuple[int, ...], owner: str) -> None:
        self.interface = interface
        self.channel = channel
        self.ids = ids
        self.owner = owner
        self._keys = [(interface, channel, i) for i in ids]

    def release(self) -> None:
        """Give the ids back (only those this claim still holds)."""
        with _lock:
            for key in self._keys:
                if _held.get(key) is self:
                    del _held[key]
            self._keys = []


def _key(interface: str, channel: object) -> tuple[str, str]:
    return str(interface).strip().lower(), str(channel).strip()


def claim(interface: str, channel: object, ids: Iterable[int], owner: str) -> Claim:
    """Hold ``ids`` on ``interface:channel`` for ``owner``; raise BusClaimedError if any is held."""
    iface, chan = _key(interface, channel)
    wanted = tuple(sorted(set(ids)))
    with _lock:
        taken: dict[Claim, list[int]] = {}
        for i in wanted:
            other = _held.get((iface, chan, i))
            if other is not None:
                taken.setdefault(other, []).append(i)
        if taken:
            who = "; ".join(
                f"motor id{'s' if len(ids_) > 1 else ''} {', '.join(map(str, ids_))} by {other.owner}"
                for other, ids_ in taken.items()
            )
            raise BusClaimedError(
                f"{iface}:{chan} is already driven in this process ({who}); close that robot first. "
                "Two controllers on one motor fight over it, and closing one disables the motor under the other"
            )
        c = Claim(iface, chan, wanted, owner)
        for i in wanted:
            _held[(iface, chan, i)] = c
    return c


def claimed(interface: str, channel: object) -> dict[int, str]:
    """The motor ids held on ``interface:channel`` in this process, with their owners (for diagnostics)."""
    iface, chan = _key(interface, channel)
    with _lock:
        return {i: c.owner for (f, ch, i), c in _held.items() if f == iface and ch == chan}
