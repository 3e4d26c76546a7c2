"""Random ROS 2 domain ids for tests, from this test process's own share of the range.

The suite runs its files in parallel worker processes (pytest-xdist, ``scripts/test.sh``). Each DDS test
puts its participants (and the processes it starts) on a random domain of their own, so unrelated tests
never discover each other; ``conftest.py`` gives every worker a disjoint share of the domains as
``AGENTSDK_TEST_DOMAINS=lo-hi`` (inherited by the processes a test starts, e.g. ``agentsdk bench``), so
two tests running at the same time in different workers cannot pick the same one either.
"""

from __future__ import annotations

import os
import random

#: the domains tests use (ROS 2's usual ids stay free: 0 and the few users pick by hand)
LOW, HIGH = 30, 230


def share(worker: int, workers: int, low: int = LOW, high: int = HIGH) -> tuple[int, int]:
    """Worker ``worker``'s (0-based, of ``workers``) disjoint part ``[lo, hi]`` of ``[low, high]``."""
    span = (high - low + 1) // max(workers, 1)
    lo = low + worker * span
    return lo, lo + span - 1


def random_domain(low: int = LOW, high: int = HIGH) -> int:
    """A random domain id in ``[low, high]`` and in this worker's share (``AGENTSDK_TEST_DOMAINS``)."""
    bounds = os.environ.get("AGENTSDK_TEST_DOMAINS")
    if bounds:
        lo, hi = (int(x) for x in bounds.split("-"))
        low, high = max(low, lo), min(high, hi)
        if low > high:
            raise ValueError(f"no domain in the requested range within this worker's share {bounds}")
    return random.SystemRandom().randint(low, high)
