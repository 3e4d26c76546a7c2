"""The suite's parallel workers pick ROS 2 domains from disjoint shares (tests/ros_domains.py)."""

from __future__ import annotations

import pytest
from ros_domains import HIGH, LOW, random_domain, share


@pytest.mark.parametrize("workers", [1, 2, 3, 8])
def test_worker_shares_are_disjoint_and_inside_the_range(workers: int) -> None:
    shares = [share(w, workers) for w in range(workers)]
    seen: set[int] = set()
    for lo, hi in shares:
        assert LOW <= lo <= hi <= HIGH
        ids = set(range(lo, hi + 1))
        assert not ids & seen
        seen |= ids


def test_random_domain_stays_in_this_workers_share(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AGENTSDK_TEST_DOMAINS", "130-229")
    assert all(130 <= random_domain() <= 229 for _ in range(200))
    assert all(130 <= random_domain(120, 140) <= 140 for _ in range(50))
    with pytest.raises(ValueError, match="130-229"):
        random_domain(30, 100)
