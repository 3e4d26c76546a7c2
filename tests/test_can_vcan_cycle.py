"""The CAN host's receive and send path on a real SocketCAN vcan0 (user-mode Linux): batched, one call per wake-up.

python-can's socketcan bus costs a ``select``, a ``recvmsg``, an interface-name ``ioctl`` and two
clock reads per received frame; in the VM every one of those traps into the guest kernel. The
backend drains the socket itself (:mod:`agentsdk.backends.can.rawsock`): one ``recvmmsg`` takes
every queued frame (up to a batch), one ``sendmmsg`` sends a cycle's commands. These tests pin
that the path is the one in use on socketcan, that a backlog is drained in batches (counted calls,
not timing), that every frame is still seen (kernel receive timestamps, foreign frames and bad
ids keep their meaning), and that the cycle keeps its replies.

    scripts/run-in-vcan.sh python -m pytest -m vcan tests/test_can_vcan_cycle.py -p no:cacheprovider
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import can
import pytest
from test_can_vcan import EMULATOR_READY, HAS_VCAN, _wait_async, leg_copy, start_emulator

import agentsdk
from agentsdk import JointCommand
from agentsdk.backends.can.rawsock import BATCH

pytestmark = [
    pytest.mark.vcan,
    pytest.mark.skipif(not HAS_VCAN, reason="no vcan0 (run via scripts/run-in-vcan.sh)"),
    pytest.mark.timeout(300),
]


async def test_socketcan_cycle_uses_batched_receive_and_one_send_call(tmp_path: Path) -> None:
    leg = leg_copy(tmp_path)
    proc = start_emulator(leg)
    try:
        await _wait_async(lambda: proc.has(EMULATOR_READY) or proc.popen.poll() is not None)
        assert proc.popen.poll() is None, proc.output()
        # the backlog below blocks the event loop on purpose while it is sent (hundreds of send
        # calls, each a trap into the guest kernel): the stall watchdog is not what this test is about
        async with agentsdk.connect("can", robot=leg, max_missed_replies=50,
                                    safety={"stall_timeout": 5.0}) as robot:
            ctl = robot.backend
            reader, writer = ctl._reader, ctl._writer  # type: ignore[attr-defined]
            assert reader is not None and writer is not None, "socketcan must use the batched path"
            assert ctl._notifier is None  # type: ignore[attr-defined]
            here = (await robot.read()).positions()
            await robot.command(JointCommand("position", here))
            await robot.clock.sleep(0.3)
            ticks0, frames0, calls0 = robot.ticks, reader.frames, reader.calls
            replies0 = sum(s.replies for s in ctl.stats)  # type: ignore[attr-defined]
            await robot.clock.sleep(1.0)
            ticks = robot.ticks - ticks0
            replies = sum(s.replies for s in ctl.stats) - replies0  # type: ignore[attr-defined]
            frames, calls = reader.frames - frames0, reader.calls - calls0
            assert ticks > 0
            # every reply came through the batched reader, at most one receive call per frame
            assert frames >= replies >= 0.8 * 3 * ticks, (frames, replies, ticks)
            assert calls <= frames, (calls, frames)

            # a backlog of foreign-id frames queued while the loop is busy: drained in batches
            unexpected0 = ctl.unexpected_replies  # type: ignore[attr-defined]
            calls0, ticks0 = reader.calls, robot.ticks
            n = 5 * BATCH
            with can.Bus(interface="socketcan", channel="vcan0") as other:
                for i in range(n):  # replies (master id 0) naming motor id 0x7e, which is not ours
                    other.send(can.Message(arbitration_id=0, data=[0x7E, 0, i & 0xFF, 0, 0, 0, 0, 0],
                                           is_extended_id=False))
                time.sleep(0.05)  # noqa: ASYNC251 - the loop is busy while the backlog queues
            # until every frame is counted (a starved VM's loop takes longer than 10 cycles of 20 ms)
            await _wait_async(lambda: ctl.unexpected_replies - unexpected0 >= n)  # type: ignore[attr-defined]
            await robot.clock.sleep(0.1)  # (and nothing more comes)
            assert ctl.unexpected_replies - unexpected0 == n  # type: ignore[attr-defined]
            # the backlog in about n / BATCH calls, not one call per frame, plus the cycles' own replies
            # meanwhile (at most one call per reply, 3 motors, counted in cycles, not assumed from time)
            cycles = max(25, robot.ticks - ticks0 + 1)
            assert reader.calls - calls0 <= math.ceil(n / BATCH) + 3 * cycles, (reader.calls - calls0, cycles)
            assert reader.calls - calls0 < n
            assert robot.safety.state is agentsdk.SafetyState.OK
    finally:
        proc.stop()
