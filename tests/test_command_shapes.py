"""The command gate's cached shapes (agentsdk.commands.CommandShapes) decide exactly what resolve_command decides.

A behavior that commands every tick reuses the joint indices of its command's shape; these tests
compare, for random and hand-picked commands (valid, unknown joints, NaN, infinities, wrong
lengths, mismatched feed-forward, repeated shapes), the cached resolver with the plain function:
the same indices and values, or the same exception type and message.
"""

from __future__ import annotations

import dataclasses
import math
import pickle
import random
from types import MappingProxyType
from typing import Any

import numpy as np
import pytest

from agentsdk import AppliedCommand, JointCommand
from agentsdk.clock import LockstepClock
from agentsdk.commands import CommandShapes, resolve_command
from agentsdk.errors import AgentSDKError, InvalidValueError

NAMES = ("a", "b", "c", "d", "e")
INDEX = {n: i for i, n in enumerate(NAMES)}
MODES = frozenset({"position", "velocity"})


def _outcome(fn: Any) -> tuple[Any, ...]:
    try:
        idx, values, vel, eff = fn()
    except AgentSDKError as exc:
        return ("error", type(exc).__name__, str(exc))
    return ("ok", idx.tolist(), values.tobytes(), None if vel is None else vel.tobytes(),
            None if eff is None else eff.tobytes())


def _random_values(rng: random.Random, keys: list[str], mapping: bool) -> Any:
    special = [math.nan, math.inf, -math.inf, 1e308, -0.0]
    vals = [rng.choice(special) if rng.random() < 0.08 else rng.uniform(-3, 3) for _ in keys]
    return dict(zip(keys, vals, strict=True)) if mapping else vals


def _random_command(rng: random.Random) -> Any:
    if rng.random() < 0.03:
        return "not a command"
    mode = rng.choice(["position", "velocity", "effort"])
    mapping = rng.random() < 0.5
    if mapping:
        pool = list(NAMES) + (["zz"] if rng.random() < 0.1 else [])
        keys = rng.sample(pool, rng.randint(1 if rng.random() < 0.95 else 0, min(3, len(pool))))
    else:
        keys = list(NAMES) if rng.random() < 0.9 else list(NAMES)[: rng.randint(0, 6)]
    values = _random_values(rng, keys, mapping)
    vel = eff = None
    if mode == "position" and rng.random() < 0.4:
        vkeys = keys if rng.random() < 0.85 else list(reversed(keys))
        vel = _random_values(rng, vkeys, mapping)
    if mode == "position" and rng.random() < 0.3:
        eff = _random_values(rng, keys, mapping)
    try:
        return JointCommand(mode, values, velocity=vel, effort=eff)
    except AgentSDKError:
        return JointCommand(mode, values)


def test_cached_shapes_decide_like_resolve_command() -> None:
    rng = random.Random(28)
    shapes = CommandShapes(NAMES, INDEX)
    for _ in range(3000):
        cmd = _random_command(rng)
        for _repeat in range(2):  # the second time the shape comes from the cache
            want = _outcome(lambda c=cmd: resolve_command(c, NAMES, INDEX, MODES, "sim"))

            def cached(c: Any = cmd) -> Any:
                idx, names, values, vel, eff = shapes.resolve(c, MODES, "sim")
                assert names == tuple(NAMES[i] for i in idx.tolist())
                return idx, values, vel, eff

            assert _outcome(cached) == want, cmd


def test_a_cached_shape_still_checks_every_value() -> None:
    shapes = CommandShapes(NAMES, INDEX)
    ok = JointCommand("position", {"c": 0.1, "a": 0.2})
    idx, names, _, _, _ = shapes.resolve(ok, MODES, "sim")
    assert idx.tolist() == [2, 0] and names == ("c", "a")
    assert not idx.flags.writeable  # shared between commands: nobody may change it
    with pytest.raises(InvalidValueError, match="non-finite value nan for joint 'a'"):
        shapes.resolve(JointCommand("position", {"c": 0.1, "a": math.nan}), MODES, "sim")
    with pytest.raises(InvalidValueError, match="non-finite value -inf for joint 'd'"):
        shapes.resolve(JointCommand("position", [0.0, 0.0, 0.0, -math.inf, 0.0]), MODES, "sim")
    # a sum that overflows is not a non-finite value
    idx, _, values, _, _ = shapes.resolve(JointCommand("velocity", [1e308] * 5), MODES, "sim")
    assert values.tolist() == [1e308] * 5


def test_the_cache_is_bounded() -> None:
    names = tuple(f"j{i}" for i in range(12))
    shapes = CommandShapes(names, {n: i for i, n in enumerate(names)})
    rng = random.Random(1)
    for _ in range(2 * CommandShapes.LIMIT):
        keys = rng.sample(names, 4)
        idx, got, _, _, _ = shapes.resolve(JointCommand("position", dict.fromkeys(keys, 0.0)), MODES, "sim")
        assert got == tuple(keys) and [names[i] for i in idx.tolist()] == keys
    assert len(shapes._by_keys) <= CommandShapes.LIMIT


def test_applied_mappings_are_read_only_copies_that_behave_as_the_dicts_they_stand_for() -> None:
    # the AppliedCommand mappings built from cached names are fresh per command, and read-only
    shapes = CommandShapes(NAMES, INDEX)
    a = shapes.resolve(JointCommand("position", [0.0] * 5), MODES, "sim")
    b = shapes.resolve(JointCommand("position", [1.0] * 5), MODES, "sim")
    assert a[0] is b[0] and a[2] is not b[2]
    values, ff = np.array([0.5, -1.0, 2.0]), np.array([0.1, 0.2, 0.3])
    names = ("c", "a", "e")
    applied = AppliedCommand.of_arrays("position", names, values, ff, None)
    values[:] = 9.0  # the arrays were copied
    expected = {"c": 0.5, "a": -1.0, "e": 2.0}
    old = AppliedCommand("position", MappingProxyType(expected),
                         MappingProxyType(dict(zip(names, [0.1, 0.2, 0.3], strict=True))), None)
    assert applied == old and old == applied  # as the dataclass of proxies compared
    assert applied.values == expected and expected == applied.values
    assert list(applied.values) == list(names) and list(applied.values.items()) == list(expected.items())
    assert len(applied.values) == 3 and "a" in applied.values and "b" not in applied.values
    assert applied.values["e"] == 2.0 and applied.velocity is not None and applied.velocity["a"] == 0.2
    assert applied.effort is None
    with pytest.raises(KeyError):
        applied.values["b"]
    with pytest.raises(TypeError):
        applied.values["a"] = 1.0  # type: ignore[index]
    with pytest.raises(dataclasses.FrozenInstanceError):
        applied.mode = "velocity"  # type: ignore[misc]
    assert applied.as_command() == JointCommand("position", expected, velocity=dict(applied.velocity))
    assert repr(applied) == repr(old)
    assert pickle.loads(pickle.dumps(applied)) == applied


@pytest.mark.parametrize(
    ("dt", "message"),
    [
        (math.nan, "sleep duration must be a number >= 0 (seconds), got nan"),
        (-0.5, "sleep duration must be a number >= 0 (seconds), got -0.5"),
        ("soon", "sleep duration must be a number of seconds, got 'soon'"),
        (np.float64(-1.0), "sleep duration must be a number >= 0 (seconds), got -1.0"),
    ],
)
async def test_lockstep_sleep_rejects_what_clock_sleep_rejects(dt: Any, message: str) -> None:
    clock = LockstepClock(0.01)
    with pytest.raises(InvalidValueError) as info:
        await clock.sleep(dt)
    assert str(info.value) == message
    assert clock.next_deadline() is None


async def test_lockstep_sleep_queues_the_same_deadlines_as_sleep_until() -> None:
    import asyncio

    clock = LockstepClock(0.01)
    for _ in range(7):
        clock.advance()
    tasks = [asyncio.ensure_future(clock.sleep(dt)) for dt in (0.03, 1, np.float64(0.02), 0.025)]
    await asyncio.sleep(0)
    now = clock.now()
    assert clock.next_deadline() == now + 0.02
    deadlines = sorted(d for d, _, _ in clock._heap)
    assert deadlines == [now + 0.02, now + 0.025, now + 0.03, now + 1.0]
    zero = asyncio.ensure_future(clock.sleep(0.0))  # no deadline: one pass through the event loop
    await asyncio.sleep(0)
    await asyncio.sleep(0)
    assert zero.done() and len(clock._heap) == 4
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
