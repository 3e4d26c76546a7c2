"""Block lockstep, the planning seam: K setpoints at once are bit for bit K single samples (issue 28 item 1)."""

from __future__ import annotations

import numpy as np
import pytest

from agentsdk.trajectory import Trajectory, TrajectoryPoint, TrajectorySampler


def _random_sampler(rng: np.random.Generator) -> TrajectorySampler:
    n = int(rng.integers(1, 9))
    m = int(rng.integers(1, 6))
    times = np.cumsum(rng.uniform(0.01, 0.7, size=m))
    if rng.random() < 0.25:
        times = times - times[0]  # point 0 at time 0: no start segment
    kind = int(rng.integers(0, 4))
    pts = []
    for t in times.tolist():
        q = rng.uniform(-3.0, 3.0, size=n)
        v = rng.uniform(-2.0, 2.0, size=n) if kind >= 2 else None
        a = rng.uniform(-5.0, 5.0, size=n) if kind == 3 else None
        pts.append(TrajectoryPoint(t, q, v, a))
    traj = Trajectory([f"j{i}" for i in range(n)], pts)
    t0 = float(rng.uniform(-5.0, 50.0))
    return TrajectorySampler(
        traj, t0, rng.uniform(-1, 1, size=n), rng.uniform(-1, 1, size=n), rng.uniform(-1, 1, size=n),
        interpolation="spline" if kind == 1 else "linear",
    )


@pytest.mark.parametrize("seed", range(8))
def test_a_block_of_samples_is_bit_for_bit_the_single_samples(seed: int) -> None:
    """Random trajectories (every interpolation), times before, across every segment and after the end."""
    rng = np.random.default_rng(seed)
    for _ in range(60):
        s = _random_sampler(rng)
        period = float(rng.choice([0.001, 0.002, 0.004, 1 / 240, 0.01]))
        start = s.start_time + float(rng.uniform(-0.1, 0.2))
        K = int(rng.integers(1, 600))
        # trajectory times as the executor accumulates them: tau += dt, one tick after another
        ts = np.add.accumulate(np.concatenate(([start], np.full(K - 1, period))))
        block = s.sample_block(ts, np.empty((K, 3, len(s.joint_names))))
        region = s.region
        single = np.empty((3, len(s.joint_names)))
        for k, t in enumerate(ts.tolist()):
            s.sample_into(t, single)
            assert block[k].tobytes() == single.tobytes(), (k, t)
        assert region == s.region  # the region of the last sample, as the tick path leaves it


def test_an_empty_block_samples_nothing() -> None:
    s = TrajectorySampler(Trajectory(["a"], [TrajectoryPoint(1.0, [1.0])]), 0.0, [0.0], [0.0], [0.0])
    out = np.empty((0, 3, 1))
    assert s.sample_block(np.empty(0), out) is out


def test_block_sampling_reports_each_sample_region() -> None:
    rng = np.random.default_rng(99)
    for _ in range(50):
        s = _random_sampler(rng)
        ts = np.sort(rng.uniform(s.start_time - 0.5, s.end_time + 0.5, size=int(rng.integers(1, 80))))
        regions = np.empty(len(ts), dtype=np.intp)
        s.sample_block(ts, np.empty((len(ts), 3, len(s.joint_names))), regions)
        single = np.empty((3, len(s.joint_names)))
        for k, t in enumerate(ts.tolist()):
            s.sample_into(t, single)
            assert regions[k] == s.region


def test_the_executor_accumulates_trajectory_time_in_tick_order() -> None:
    """np.add.accumulate adds left to right, as the tick does ``tau += dt`` (no pairwise summation)."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        x = rng.uniform(-1e3, 1e3, size=int(rng.integers(1, 2000))) * 10 ** rng.uniform(-6, 2)
        acc, seq = np.add.accumulate(x), []
        total = 0.0
        for i, v in enumerate(x.tolist()):
            total = v if i == 0 else total + v
            seq.append(total)
        assert acc.tobytes() == np.array(seq).tobytes()


def test_samples_exactly_at_the_knots_take_the_segment_a_single_sample_takes() -> None:
    """Times that are knots (and repeat): each lands in the segment bisect_right picks, as sample_into."""
    rng = np.random.default_rng(17)
    for _ in range(60):
        s = _random_sampler(rng)
        knots = [s.start_time, *(s.start_time + np.asarray([p.time_from_start for p in s.trajectory.points])).tolist()]
        ts = np.sort(np.concatenate((knots, knots, rng.uniform(s.start_time - 0.2, s.end_time + 0.2, size=20))))
        regions = np.empty(len(ts), dtype=np.intp)
        block = s.sample_block(ts, np.empty((len(ts), 3, len(s.joint_names))), regions)
        single = np.empty((3, len(s.joint_names)))
        for k, t in enumerate(ts.tolist()):
            s.sample_into(t, single)
            assert regions[k] == s.region, (k, t)
            assert block[k].tobytes() == single.tobytes(), (k, t)
