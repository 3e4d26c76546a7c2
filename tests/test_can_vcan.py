"""CAN backend on a real SocketCAN ``vcan0``, the motor emulator in a separate process.

Skipped unless ``/sys/class/net/vcan0`` exists; run inside user-mode Linux::

    scripts/run-in-vcan.sh /work/venv/bin/python -m pytest tests/test_can_vcan.py -m vcan -q -p no:cacheprovider

Here the event loop reads the bus itself (``loop.add_reader`` on the socket) and the
motors are another process, like real hardware.

Control rate: mit_leg's robot.yaml asks for 500 Hz, but user-mode Linux has one vCPU and
pays a host-level context switch per guest process switch: a raw 3-motor round trip
(3 commands out, 3 replies back, emulator in another process) measured 3.7 ms median,
12 ms p99 there (0.2 ms on the host's own kernel), so a 2 ms cycle with a 1.6 ms reply
deadline cannot be met and the backend rightly faults. The suite therefore runs a copy
of mit_leg's robot.yaml at ``AGENTSDK_VCAN_RATE`` Hz (default 50: 20 ms cycles, 16 ms
reply deadline; at 100 Hz a loaded host missed a third of the cycles in UML, where every clock
read and socket call is a trap into the guest kernel), with the motors' command timeout at
0.25 s (:data:`MOTOR_TIMEOUT`: CI's VM stalls for longer than mit_leg's 25 ms, and a motor that
goes limp mid-move coasts past its limit); set ``AGENTSDK_VCAN_RATE=500`` and
``AGENTSDK_VCAN_MOTOR_TIMEOUT=0.025`` on a machine with a native vcan0 to run the robot.yaml
unchanged. Every emulator and host process is terminated in a ``finally``; frames are observed
with independent ``can.Bus("vcan0")`` handles and their kernel receive timestamps.

Motor-side timeout after ``kill -9`` of the host: the emulator process has no status
channel, so the test observes the bus. While the host streams velocity commands the
motors' replies carry a clear torque; after the kill no DISABLE frame appears (the host
died) and, once the firmware timeout (:data:`MOTOR_TIMEOUT`) has passed, a CLEAR_ERROR frame (``FF..FB``,
which the emulator answers without touching kp/kd/t_ff) probes each motor: its reply
reports the torque the firmware applies at that moment, which must be 0 (limp).
(Emulator only: CubeMars firmware has no ``FB`` frame and would read it as a command.)
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar

import can
import numpy as np
import pytest
import yaml

import agentsdk
from agentsdk import JointCommand, Robot
from agentsdk.backends.can.config import load_can_config
from agentsdk.backends.can.mit import CLEAR_ERROR, DISABLE, decode_reply, is_special, profile_for
from agentsdk.testing import BackendConformance

ROOT = Path(__file__).resolve().parents[1]
HAS_VCAN = Path("/sys/class/net/vcan0").exists()

pytestmark = [
    pytest.mark.vcan,
    pytest.mark.skipif(not HAS_VCAN, reason="no vcan0 (run via scripts/run-in-vcan.sh)"),
    # process start-up (imports through hostfs, every stat a trap into the guest kernel) takes tens of
    # seconds on a slow CI machine's VM: the suite's default 120 s is for tests in one process
    pytest.mark.timeout(600),
]

#: mit_leg's motors: CAN id -> joint
MOTORS = {1: "hip_abduction", 2: "hip_pitch", 3: "knee"}
#: hang guard for process start-up (Python + numpy + MuJoCo imports under user-mode Linux; CI's VM is slow)
STARTUP_LIMIT = 150.0
#: control rate of the robot under test (see the module docstring)
VCAN_RATE = float(os.environ.get("AGENTSDK_VCAN_RATE", "50"))
#: the motors' own command timeout (firmware setting) in the copy: mit_leg's 25 ms is 12 cycles at 500 Hz;
#: in the VM 0.25 s (and at least 2.5 periods): a stall of the VM's one vCPU (tens of ms on a slow CI
#: machine) must not make a motor go limp mid-move, where the free rotor coasts past the joint's limit
MOTOR_TIMEOUT = float(os.environ.get("AGENTSDK_VCAN_MOTOR_TIMEOUT", max(0.25, 2.5 / VCAN_RATE)))


@pytest.fixture(scope="module")
def leg(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A copy of mit_leg's robot.yaml at VCAN_RATE for connect, the emulator and the CLI.

    Without gravity compensation: the emulator's free rotors feel no gravity, so the g(q)
    feed-forward would act on them as a disturbance torque (a velocity stream then tracks
    ~0.4 rad/s short on the knee, ff/kd). The MuJoCo-plant test below turns it on.
    """
    return leg_copy(tmp_path_factory.mktemp("robots"), gravity_compensation=False)


def leg_copy(directory: Path, **changes: Any) -> str:
    """A copy of mit_leg's robot.yaml at VCAN_RATE with other robot.yaml ``changes``."""
    src = ROOT / "robots" / "mit_leg" / "robot.yaml"
    cfg = yaml.safe_load(src.read_text())
    cfg["description"] = str(src.parent / cfg["description"])
    cfg["update_rate"] = VCAN_RATE
    cfg["backends"]["can"]["timeout"] = MOTOR_TIMEOUT
    cfg["inverse_dynamics"] = False  # the free-rotor emulator has none of the leg's dynamics (the plant test sets it)
    cfg.update(changes)  # may set another update_rate
    dst = directory / "mit_leg" / "robot.yaml"
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(yaml.safe_dump(cfg))
    return str(dst)


# --------------------------------------------------------------------- processes
class Proc:
    """A child process whose stdout+stderr go to a file (nothing to drain, nothing to block)."""

    def __init__(self, argv: list[str], name: str) -> None:
        fd, path = tempfile.mkstemp(prefix=f"agentsdk-{name}-", suffix=".log")
        self.log_path = Path(path)
        with os.fdopen(fd, "wb") as log:
            self.popen = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def has(self, text: str) -> bool:
        return text in self.output()

    def wait_for(self, text: str, limit: float = STARTUP_LIMIT) -> None:
        deadline = time.monotonic() + limit
        while not self.has(text):
            if self.popen.poll() is not None:
                pytest.fail(f"process exited {self.popen.returncode} before {text!r}:\n{self.output()}")
            if time.monotonic() > deadline:
                pytest.fail(f"no {text!r} within {limit} s:\n{self.output()}")
            time.sleep(0.02)

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.terminate()
            try:
                self.popen.wait(10)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
        with contextlib.suppress(OSError):
            self.log_path.unlink()


#: run the emulated motors at a real-time priority of the guest's scheduler (as root, where ``chrt`` exists):
#: real motors are separate hardware whose replies do not wait for the host's CPU, while user-mode
#: Linux has one vCPU shared by the emulator, pytest and the robot's loop. A busy host then cannot
#: delay the motors' replies past the reply deadline; the host's own delays still count.
MOTOR_PRIORITY = (["chrt", "--fifo", "10"]
                  if os.geteuid() == 0 and shutil.which("chrt") and os.environ.get("AGENTSDK_VCAN_MOTOR_RT", "1") == "1"
                  else [])


def start_emulator(robot: str, *args: str, realtime: bool = True) -> Proc:
    """The motor emulator process on vcan0 (``realtime``: at :data:`MOTOR_PRIORITY`)."""
    return Proc(
        [*(MOTOR_PRIORITY if realtime else []), sys.executable, "-m", "agentsdk.backends.can.emulator",
         "--robot", robot, "--interface", "socketcan", "--channel", "vcan0", *args],
        "emulator",
    )


EMULATOR_READY = "emulating mit_leg on socketcan:vcan0"


@contextlib.contextmanager
def emulator_process(robot: str, *args: str) -> Iterator[Proc]:
    proc = start_emulator(robot, *args)
    try:
        proc.wait_for(EMULATOR_READY)
        yield proc
    finally:
        proc.stop()


def agentsdk_run(behavior: Path | str, robot: str, *args: str) -> Proc:
    """``agentsdk run BEHAVIOR --backend can --robot ROBOT ARGS`` as a child process."""
    return Proc(
        [sys.executable, "-c", "import sys; from agentsdk.cli import main; sys.exit(main())",
         "run", str(behavior), "--backend", "can", "--robot", robot, *args],
        "host",
    )


class Recorder:
    """An independent listener on vcan0: a thread collects every frame (kernel timestamps)."""

    def __init__(self) -> None:
        self.bus = can.Bus(interface="socketcan", channel="vcan0")
        self._frames: list[can.Message] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="vcan-recorder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                with self._lock:
                    self._frames.append(msg)

    def frames(self) -> list[can.Message]:
        with self._lock:
            return list(self._frames)

    def frames_until(self, t_wall: float, timeout: float = 10.0) -> list[can.Message]:
        """The frames the kernel stamped at or before ``t_wall`` (``time.time()``), once this thread has
        taken one stamped after it: a starved thread may still be draining its socket when asked."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            frames = self.frames()
            if frames and frames[-1].timestamp > t_wall:
                break
            time.sleep(0.01)
        else:
            raise AssertionError(f"no frame stamped after {t_wall:.3f} reached the recorder in {timeout} s")
        return [m for m in frames if m.timestamp <= t_wall]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.bus.shutdown()


@contextlib.contextmanager
def recorder() -> Iterator[Recorder]:
    rec = Recorder()
    try:
        yield rec
    finally:
        rec.close()


def commands(frames: list[can.Message]) -> list[can.Message]:
    """Command frames to the motors (not special frames, not replies)."""
    return [m for m in frames if m.arbitration_id in MOTORS and is_special(m.data) is None]


def disables(frames: list[can.Message]) -> list[can.Message]:
    return [m for m in frames if m.arbitration_id in MOTORS and bytes(m.data) == DISABLE]


def write_behavior(directory: Path, name: str, body: str) -> Path:
    path = directory / f"{name}.py"
    path.write_text(body)
    return path


# --------------------------------------------------------------------- conformance
class TestCanConformanceVcan(BackendConformance):
    """The backend contract on socketcan vcan0 (robot.yaml: socketcan, vcan0; rate VCAN_RATE),
    each test with a fresh emulator process. Kit tolerances unchanged; more missed replies tolerated."""

    backend = "can"
    robot = "mit_leg"
    #: replies the kit's tests tolerate missing in a row: user-mode Linux's one vCPU, shared by the emulator,
    #: pytest and the loop, is descheduled by a busy host now and then, and a reply that leaves the VM 10 ms
    #: late is a missed cycle (the backend's default, 5, is for real hardware; the fault rule itself is
    #: tested on the virtual bus in tests/test_can_backend.py); likewise a 1 s stall watchdog instead of 0.25 s
    #: (the kit's own stall test sets its 0.1 s)
    connect_options: ClassVar[dict[str, Any]] = {"max_missed_replies": 25, "safety": {"stall_timeout": 1.0}}

    @pytest.fixture(autouse=True)
    def _robot_at_vcan_rate(self, leg: str) -> None:
        type(self).robot = leg  # the free-motor emulator has no gravity to compensate

    @contextlib.asynccontextmanager
    async def open_robot(self, **overrides: Any) -> AsyncIterator[Robot]:
        proc = start_emulator(self.robot)
        try:
            await _wait_async(lambda: proc.has(EMULATOR_READY) or proc.popen.poll() is not None)
            assert proc.popen.poll() is None, proc.output()
            opts = {**self.connect_options, **overrides}
            async with agentsdk.connect(self.backend, robot=self.robot, realtime=self.realtime, **opts) as robot:
                yield robot
        finally:
            proc.stop()


async def _wait_async(predicate: Callable[[], bool], limit: float = STARTUP_LIMIT) -> None:
    async with asyncio.timeout(limit):
        while not predicate():  # noqa: ASYNC110 - the emulator is another process
            await asyncio.sleep(0.02)


# --------------------------------------------------------------------------- gravity feed-forward (issue 13)
#: control rate against the MuJoCo-plant emulator (its physics shares UML's one vCPU with the host)
PLANT_RATE = float(os.environ.get("AGENTSDK_VCAN_PLANT_RATE", "50"))


async def test_gravity_feedforward_holds_mit_leg_on_the_mujoco_plant_over_vcan0(tmp_path: Path) -> None:
    """mit_leg against the MuJoCo-plant emulator process: the host's g(q) as the MIT torque feed-forward
    holds the start pose within 0.01 rad; without it the leg sags by about g/kp.

    The plant keeps up in the VM because ``emulate-can --plant mujoco`` turns MuJoCo's profiling
    timers off (about 30 clock reads per ``mj_step``, each a system call in user-mode Linux: the plant
    needed the whole vCPU and, at its real-time priority, starved the host) and steps MuJoCo in
    batches between frames (:class:`~agentsdk.backends.can.emulator.Plant`).
    """
    drift: dict[bool, float] = {}
    traces: dict[bool, list[list[float]]] = {}
    for on in (True, False):
        # the MuJoCo plant in another process on UML's one vCPU: a slower cycle it can close, missed replies tolerated
        robot_yaml = leg_copy(tmp_path / str(on), gravity_compensation=on, inverse_dynamics=on, update_rate=PLANT_RATE)
        proc = start_emulator(robot_yaml, "--plant", "mujoco", "--substep", "0.002", "--timeout", "0.25")
        try:
            await _wait_async(lambda p=proc: p.has(EMULATOR_READY) or p.popen.poll() is not None)
            assert proc.popen.poll() is None, proc.output()
            async with agentsdk.connect("can", robot=robot_yaml, open_timeout=2.0, max_missed_replies=50) as robot:
                q0 = np.array([robot.backend.initial_positions[k] for k in range(len(robot.joints))])
                await robot.command(JointCommand("position", dict(zip(robot.joint_names, q0.tolist(), strict=True))))
                await robot.clock.sleep(0.3)  # the motors were limp until enabled
                trace = []
                for _ in range(50):
                    await robot.clock.sleep(0.04)
                    trace.append(np.round((await robot.read()).position - q0, 4).tolist())
                # the median excursion: UML's one vCPU stalls now and then (missed replies, the plant skips
                # physics), which kicks the leg whatever the feed-forward; the peak is in the message
                drift[on] = float(np.median(np.abs(np.array(trace)).max(axis=1)))
                traces[on] = trace
                assert bool(np.abs(robot.backend.gravity_torque).max() > 0.1) is on
        except agentsdk.AgentSDKError as exc:
            pytest.fail(f"{exc}\nemulator output:\n{proc.output()[-3000:]}")
        finally:
            proc.stop()
    print(f"vcan0 @ {PLANT_RATE:g} Hz, mit_leg on the MuJoCo plant: hold drift with g(q) "
          f"{drift[True]:.5f} rad, without {drift[False]:.5f} rad")
    assert drift[True] < 0.01, (drift, traces[True])
    assert drift[False] > 2 * drift[True], drift


# --------------------------------------------------------------------------- CLI
@pytest.mark.timeout(360)
def test_agentsdk_run_wave_on_vcan0(leg: str) -> None:
    # no -o options: interface socketcan and channel vcan0 come from the robot.yaml
    with emulator_process(leg) as emu, recorder() as rec:
        host = agentsdk_run(ROOT / "behaviors" / "wave.py", leg)
        try:
            rc = host.popen.wait(240)  # 7.5 s of wave; process start-up takes tens of seconds in a slow VM
        except subprocess.TimeoutExpired:
            pytest.fail(f"wave.py did not end within 240 s:\n{host.output()[-4000:]}\n"
                        f"emulator:\n{emu.output()[-2000:]}")
        finally:
            out = host.output()
            host.stop()
        assert rc == 0, out
        assert f"ran wave.py on {leg} (can)" in out
        frames = rec.frames()
        # the host streamed to every motor for the whole 7.5 s wave. Not a count against the rate: a starved VM
        # skips periods (skipped, never queued), and one CI run sent 396 frames where 3 x 7.5 s x 50 Hz is 1125
        sent = commands(frames)
        for motor in MOTORS:
            stamps = [f.timestamp for f in sent if f.arbitration_id == motor]
            assert len(stamps) > 2 * 7.5, (motor, len(stamps))  # at least 2 a second
            assert stamps[-1] - stamps[0] > 7.0, (motor, stamps[-1] - stamps[0])
        assert {m.arbitration_id for m in disables(frames)} == set(MOTORS)  # close disabled them


# ----------------------------------------------------------------- kill -9 of the host
STREAM_BEHAVIOR = """\
from agentsdk import JointCommand

async def main(robot):
    # stream velocity commands until killed, back and forth in the middle of each joint's range
    # (the safety layer would stop a stream at a position limit)
    names = [j.name for j in robot.joints]
    mid = {j.name: 0.5 * (j.lower + j.upper) for j in robot.joints}
    half = {j.name: 0.15 * (j.upper - j.lower) for j in robot.joints}
    sign = {name: 1.0 for name in names}
    n = 0
    while True:
        q = (await robot.read()).positions()
        for name in names:
            if (q[name] - mid[name]) * sign[name] > half[name]:
                sign[name] = -sign[name]
        # 1 rad/s: a starved VM may see the reversal point late, and 0.35 of the range is left before the limit
        await robot.command(JointCommand("velocity", {name: 1.0 * sign[name] for name in names}))
        n += 1
        if n == 50:
            print("STREAMING", flush=True)
        await robot.clock.sleep(0.01)
"""


def _probe(bus: can.BusABC, profile: Any, ranges: dict[int, Any], limit: float = 2.0) -> dict[int, Any]:
    """CLEAR_ERROR to every motor; their decoded replies by motor id."""
    while bus.recv(0.0) is not None:  # drop what is queued
        pass
    for mid in MOTORS:
        bus.send(can.Message(arbitration_id=mid, data=CLEAR_ERROR, is_extended_id=False))
    replies: dict[int, Any] = {}
    deadline = time.monotonic() + limit
    while len(replies) < len(MOTORS) and time.monotonic() < deadline:
        msg = bus.recv(0.05)
        if msg is not None and msg.data[0] in MOTORS:
            replies[msg.data[0]] = decode_reply(msg.data, ranges[msg.data[0]], profile)
    assert set(replies) == set(MOTORS), f"probe replies only from {sorted(replies)}"
    return replies


#: replies per motor the kill -9 test looks back over to see the motors moving with torque on
LIVE_REPLIES = max(3, round(0.15 * VCAN_RATE))


def test_kill_9_of_the_host_leaves_the_motors_limp_by_their_own_timeout(tmp_path: Path, leg: str) -> None:
    _, cfg = load_can_config(leg)
    profile = profile_for(cfg.profile)
    ranges = {m.id: m.motor_ranges for m in cfg.motors.values()}
    lsb = {mid: r.lsb("t") for mid, r in ranges.items()}
    behavior = write_behavior(tmp_path, "stream", STREAM_BEHAVIOR)
    with emulator_process(leg), recorder() as rec, can.Bus(
        interface="socketcan", channel="vcan0", can_filters=[{"can_id": cfg.master_id, "can_mask": 0x7FF}]
    ) as probe_bus:
        host = agentsdk_run(behavior, leg)
        try:
            host.wait_for("STREAMING")
            time.sleep(0.3)
            # alive: the host's own traffic shows the motors moving and working (over each motor's last
            # LIVE_REPLIES replies, ~150 ms at 50 Hz: a reversal may be under way at any single instant;
            # counted in replies, not wall time: a starved VM's host or recorder thread lags for 100s of ms)
            live: dict[int, list[Any]] = {mid: [] for mid in MOTORS}
            for msg in reversed(rec.frames()):
                if msg.arbitration_id == cfg.master_id and msg.data[0] in live:
                    reps = live[msg.data[0]]
                    if len(reps) < LIVE_REPLIES:
                        reps.append(decode_reply(msg.data, ranges[msg.data[0]], profile))
                if all(len(r) == LIVE_REPLIES for r in live.values()):
                    break
            for mid, reps in live.items():
                assert len(reps) == LIVE_REPLIES, f"only {len(reps)} replies from motor {mid}"
                assert max(abs(r.velocity) for r in reps) > 0.75, (mid, reps[:3])
                assert max(abs(r.torque) for r in reps) > 2 * lsb[mid], (mid, reps[:3])  # torque on (limp: < 1 LSB)
            os.kill(host.popen.pid, signal.SIGKILL)
            t_kill = time.monotonic()
            assert host.popen.wait(10) == -signal.SIGKILL
            # the host is dead from here on: on the kernel's clock, which stamps each frame as it is sent (the
            # recorder thread may still be draining frames sent before the kill, so a count taken now is not it)
            t_dead = time.time()
        finally:
            host.stop()
        time.sleep(max(0.0, t_kill + 2.4 * MOTOR_TIMEOUT - time.monotonic()))  # > 2x the firmware timeout
        t_probe = time.monotonic() - t_kill
        after = [m for m in rec.frames() if m.timestamp > t_dead]
        limp = _probe(probe_bus, profile, ranges)
        time.sleep(1.0)
        stopped = _probe(probe_bus, profile, ranges)
    assert not disables(rec.frames()), "the killed host cannot have sent DISABLE"
    assert not commands(after), "no command may follow the kill"
    for mid in MOTORS:
        # no torque (the zero code decodes to half an LSB), while the rotor still coasts
        assert abs(limp[mid].torque) < lsb[mid], (mid, limp[mid], t_probe)
        assert abs(stopped[mid].torque) < lsb[mid], (mid, stopped[mid])
        assert abs(stopped[mid].velocity) < max(abs(r.velocity) for r in live[mid]) / 4, (mid, stopped[mid])
    print(f"probe {t_probe * 1e3:.0f} ms after SIGKILL: torques "
          f"{[round(limp[m].torque, 4) for m in MOTORS]} N·m, velocities {[round(limp[m].velocity, 2) for m in MOTORS]}"
          f" rad/s (live up to {[round(max(abs(r.torque) for r in live[m]), 3) for m in MOTORS]} N·m)")


# ------------------------------------------------------------------ event-loop stall
STALL_BEHAVIOR = """\
import time

from agentsdk import JointCommand

async def main(robot):
    await robot.command(JointCommand("position", {"knee": 0.7}))
    await robot.clock.sleep(0.5)
    print("STALL", flush=True)
    time.sleep(1.0)  # blocks the event loop
    print("AFTER", robot.safety.state.name, flush=True)
    print("LATENCY", robot.safety.stall_latency, flush=True)
"""


def test_event_loop_stall_sends_disable_from_the_watchdog(tmp_path: Path, leg: str) -> None:
    stall_timeout = agentsdk.SafetyConfig().stall_timeout
    assert stall_timeout is not None
    behavior = write_behavior(tmp_path, "stall", STALL_BEHAVIOR)
    with emulator_process(leg), recorder() as rec:
        host = agentsdk_run(behavior, leg)
        try:
            rc = host.popen.wait(120)
            out = host.output()
        finally:
            host.stop()
        frames = rec.frames()
    assert rc == 0, out
    assert "AFTER ESTOP" in out, out
    off = disables(frames)
    first = off[0]
    # the first DISABLE burst (the watchdog's), one per motor, before the loop runs again
    burst = [m for m in off if m.timestamp - first.timestamp < 0.05]
    assert {m.arbitration_id for m in burst} == set(MOTORS)
    last_cmd = max(m.timestamp for m in commands(frames) if m.timestamp < first.timestamp)
    gap = first.timestamp - last_cmd
    resumed = [m for m in commands(frames) if m.timestamp > first.timestamp]
    latency = float(out.split("LATENCY", 1)[1].split()[0])
    print(f"loop stalled; DISABLE {gap * 1e3:.1f} ms after the last command, {latency * 1e3:.1f} ms after"
          f" the last heartbeat (stall_timeout {stall_timeout} s)")
    # never before stall_timeout has passed without a heartbeat, and soon after
    assert stall_timeout <= latency < stall_timeout + 0.15, latency
    # On the wire: the last tick beat at the time it read before computing and writing its
    # command, so the command goes out after the beat by the tick's own duration (a few ms; tens
    # of ms in a loaded user-mode Linux, where CI saw 225.7 ms with the 250 ms timeout).
    assert stall_timeout / 2 < gap < stall_timeout + 0.15, gap
    # the loop was still stuck for ~0.75 s after the DISABLE burst: nothing else was sent meanwhile
    assert not resumed or resumed[0].timestamp - first.timestamp > 0.5


# ------------------------------------------------------------------ signals (issue 10.1)
SIGNAL_BEHAVIOR = """\
from agentsdk import Trajectory, TrajectoryPoint

async def main(robot):
    q = (await robot.read()).positions()   # the emulated leg stays where the last trial left it
    knee = 1.9 if q["knee"] < 1.35 else 0.8
    hip = 0.3 if q["hip_pitch"] < 0.0 else -0.4
    motion = robot.follow(Trajectory(["hip_pitch", "knee"], [TrajectoryPoint(2.0, [hip, knee])]))
    # well into the move, measured: a starved VM lags the plan (the test also checks it moved)
    await robot.clock.sleep(0.4)
    for _ in range(60):
        if max(abs(v) for v in (await robot.read()).velocity) > 0.4:
            break
        await robot.clock.sleep(0.02)
    print("MOVING", flush=True)
    await motion   # the README's own pattern
"""
SIGNAL_TRIALS = int(os.environ.get("AGENTSDK_SIGNAL_TRIALS", "4"))  # each of the 4 signal offsets once


@pytest.mark.timeout(900)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_stops_the_motors_at_rest_before_disabling_them(tmp_path: Path, leg: str, sig: int) -> None:
    """Ctrl-C/SIGTERM mid-trajectory: a category 1 stop to rest, then DISABLE; exit 128 + signal.

    Before the fix the knee was disabled at 0.69 rad/s and coasted (a category 0 stop). The host
    records its run; the test reads back the measured velocity when torque was removed.
    """
    from agentsdk.recording import read_recording

    behavior = write_behavior(tmp_path, "move", SIGNAL_BEHAVIOR)
    # recording every tick in realtime on the VM's one vCPU: the writer thread and the loop share it,
    # and the 0.25 s default stall timeout fired there, and in a starved VM even 1 s did (the whole host
    # process unscheduled for 1.2 s inside a timerfd syscall); this test is about signals, so it allows
    # 5 s, as the trust tests do (the stall watchdog has its own test above)
    host_leg = leg_copy(tmp_path / "host", gravity_compensation=False, safety={"stall_timeout": 5.0})
    with emulator_process(leg):
        for k in range(SIGNAL_TRIALS):
            record = tmp_path / f"run-{sig}-{k}.mcap"
            # every tick (a rate at or above the control rate): the test reads the state at torque-off;
            # 100 missed reply cycles tolerated, as the README's CAN quickstart does in the VM (its one vCPU
            # runs the emulator, the host and the kernel: replies miss the deadline for a few cycles)
            host = agentsdk_run(behavior, host_leg, "--quiet", "--record", str(record), "--record-rate", "1e6",
                                "-o", "max_missed_replies=100")
            try:
                host.wait_for("MOVING")
                time.sleep(0.05 * (k % 4))
                host.popen.send_signal(sig)
                rc = host.popen.wait(60)
                out = host.output()
            finally:
                host.stop()
            assert rc == 128 + sig, f"trial {k}: exit {rc}\n{out}"
            assert "never retrieved" not in out and "Traceback" not in out, out
            assert f"interrupted by {signal.Signals(sig).name}: category 1: stopped, torque removed" in out, out
            data = read_recording(record)
            (ev,) = [e for e in data.events if e["detail"] == "category 1: stopped, torque removed"]
            t_off = round(ev["time"] * 1e9)
            before = np.flatnonzero(data.state_time <= t_off)
            # (moving: twice the at-rest bound below; the knee's planned speed there is 0.36..0.95 rad/s, less
            # what the emulated rotor lags when the VM is starved)
            assert np.abs(data.velocity[before]).max() > 0.2, f"trial {k}: was not moving"
            v_off = np.abs(data.velocity[before[-1]]).max()
            assert v_off < 0.1, f"trial {k}: motors disabled at {v_off:.3f} rad/s (category 0, not 1)"


# ------------------------------------------------------------ set_zero (issue 10, item 7) and close
async def _settle(robot: Robot, joint: str, target: float | None = None, limit: float = 10.0) -> float:
    """Wait until ``joint`` is at rest (and at ``target`` if given); returns its position."""
    async with asyncio.timeout(limit):
        while True:
            st = await robot.read()
            k = robot.joint_index[joint]
            q, v = float(st.position[k]), float(st.velocity[k])
            if abs(v) < 0.02 and (target is None or abs(q - target) < 0.01):
                return q
            await robot.clock.sleep(0.02)


async def test_set_zero_on_vcan0_refused_with_torque_on_then_zeroes_without_moving(
    leg: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: the zero frame went out while holding and the old target moved the knee (0.655 rad).

    Also: no bus call that can block runs on the event loop (sends without a timeout,
    joining a reader thread, shutting the socket down), through set_zero, enable and close.
    """
    from can.interfaces.socketcan import SocketcanBus

    loop_thread = threading.get_ident()
    blocking: list[str] = []
    real_send, real_stop = SocketcanBus.send, can.Notifier.stop

    def send(self: SocketcanBus, msg: can.Message, timeout: float | None = None) -> None:
        if threading.get_ident() == loop_thread and (timeout is None or timeout > 0.02):
            blocking.append(f"send(timeout={timeout})")
        real_send(self, msg, timeout)

    def stop(self: can.Notifier, timeout: float = 5.0) -> None:
        if threading.get_ident() == loop_thread and timeout > 0:
            blocking.append(f"Notifier.stop(timeout={timeout})")
        real_stop(self, timeout)

    monkeypatch.setattr(SocketcanBus, "send", send)
    monkeypatch.setattr(can.Notifier, "stop", stop)
    proc = start_emulator(leg)
    try:
        await _wait_async(lambda: proc.has(EMULATOR_READY) or proc.popen.poll() is not None)
        assert proc.popen.poll() is None, proc.output()
        # the conformance kit's VM tolerances (missed replies, stall watchdog): a slow VM's stalls are not this test
        async with agentsdk.connect("can", robot=leg, **TestCanConformanceVcan.connect_options) as robot:
            await robot.command(agentsdk.JointCommand("position", {"knee": 0.6}))
            await _settle(robot, "knee", 0.6)
            with pytest.raises(agentsdk.CommandRejected, match=r"set_zero\('knee'\) refused"):
                await robot.backend.set_zero("knee")
            await robot.clock.sleep(0.5)
            assert await _settle(robot, "knee") == pytest.approx(0.6, abs=0.01)  # nothing moved

            await robot.estop(0)
            await robot.reset()
            await _settle(robot, "knee")
            await robot.backend.set_zero("knee")
            assert (await robot.read()).positions()["knee"] == pytest.approx(0.0, abs=0.02)
            await robot.enable()  # holds the knee where it is: 0 in the new frame
            await robot.clock.sleep(0.5)
            assert await _settle(robot, "knee") == pytest.approx(0.0, abs=0.02)
            assert robot.safety.state is agentsdk.SafetyState.OK
    finally:
        proc.stop()
    assert blocking == []

