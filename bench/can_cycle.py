"""CAN control-cycle rates for 1, 3, 6 and 12 MIT motors, next to raw python-can and the wire limit.

Not a test. For each motor count N it generates a robot (URDF with N revolute joints plus a
robot.yaml whose ``agentsdk.backends.can`` maps them to CubeMars AK80-9 motors, ids 1..N) in a temp
directory, starts the MIT motor emulator for it, and measures against that same emulator:

wire limit         the 1 Mbit/s classic-CAN bound (PROTOCOLS.md section 4): one 8-byte command
                   plus one reply (DLC of the profile: 8 for cubemars) per motor per cycle;
                   frame bits = 47 + 8*DLC unstuffed, plus up to (34 + 8*DLC - 1) // 4 stuff bits.
                   vcan has no bit timing, so the measured rates may exceed it.
raw sync           python-can alone, blocking: ``send`` N command frames, ``recv`` until N replies, repeat.
raw async          the same round trip the way the backend receives: a ``can.Notifier`` on the
                   asyncio loop (``add_reader`` on socketcan; a reader thread on ``virtual``), an
                   event set when the N-th reply is in.
backend free-run   the CAN backend's own bus cycle, back to back: the backend's public methods
                   ``write`` (encode N commands) -> ``await step(dt)`` (send, wait for the N replies
                   via its Notifier) -> ``read`` (decode into joint state), with ``dt = 50 ms`` so
                   that the wait always ends at the last reply, never at the deadline. This is the
                   achievable closed-loop rate of the backend (no pacing, no safety layer).
backend realtime   the whole stack: ``agentsdk.connect("can", ...)`` with ``update_rate`` set to
                   ``--rate`` (default 2000 Hz), holding position for the duration: control ticks
                   per second, missed deadlines (periods skipped), and the fraction of motor-cycles
                   whose reply missed the reply deadline (counted missed; ``late`` = came after it).
                   Run a second time at ``--sustain`` (default 0.5) x the free-running rate: does
                   the stack hold a rate with that much headroom without misses?

Usage (a real SocketCAN vcan0, e.g. inside ``scripts/run-in-vcan.sh``)::

    scripts/run-in-vcan.sh /work/venv/bin/python bench/can_cycle.py
    python bench/can_cycle.py --interface virtual        # quick look without vcan0 (emulator = thread)
    python bench/can_cycle.py --motors 1,3 --duration 1 --rate 1000 --json out.json

On socketcan the emulator is a separate process (``python -m agentsdk.backends.can.emulator``), like
real motors; on ``virtual`` it has to be a thread of this process, sharing the GIL, so the
virtual figures are pessimistic. Prints a table, then the results as JSON.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # python bench/can_cycle.py
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import can
import yaml

import agentsdk
from agentsdk.backends.can.emulator import MotorEmulator
from agentsdk.backends.can.mit import encode_command, profile_for, ranges_for
from agentsdk.bench.can_emulator import emulator_process
from agentsdk.description import apply_overrides, resolve_robot
from agentsdk.loop import Setpoint
from agentsdk.registry import load_backend

ROOT = Path(__file__).resolve().parents[1]
MOTOR_COUNTS = (1, 3, 6, 12)
MODEL = "AK80-9"
PROFILE = "cubemars"
MASTER_ID = 0
BITRATE = 1_000_000


# ------------------------------------------------------------------------------ wire limit
def frame_bits(dlc: int) -> tuple[int, int]:
    """(unstuffed, worst-case stuffed) bits of a classic CAN 2.0A data frame, incl. 3 bits interframe space."""
    bits = 47 + 8 * dlc  # SOF, 11-bit id, RTR, IDE, r0, DLC, data, CRC 15 + delim, ACK 2, EOF 7, IFS 3
    stuffable = 34 + 8 * dlc  # SOF .. CRC
    return bits, bits + (stuffable - 1) // 4


def wire_limit(n: int, reply_dlc: int) -> dict[str, float]:
    """Max closed-loop rate of ``n`` motors at 100 % bus load (one 8-byte command + one reply each)."""
    cmd, cmd_worst = frame_bits(8)
    rep, rep_worst = frame_bits(reply_dlc)
    return {
        "bits_per_motor_best": cmd + rep,
        "bits_per_motor_worst": cmd_worst + rep_worst,
        "hz_best": BITRATE / (n * (cmd + rep)),
        "hz_worst": BITRATE / (n * (cmd_worst + rep_worst)),
    }


# ------------------------------------------------------------------------------ test robot
def write_robot(directory: Path, n: int, rate: float, interface: str, channel: str) -> Path:
    """URDF with ``n`` revolute joints and a robot.yaml mapping them to motors 1..n; returns the yaml."""
    d = directory / f"can_bench_{n}"
    d.mkdir(parents=True, exist_ok=True)
    links = ['  <link name="base"><inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" '
             'iyy="0.01" iyz="0" izz="0.01"/></inertial></link>']
    parent = "base"
    for i in range(1, n + 1):
        links.append(
            f'  <link name="link{i}"><inertial><mass value="0.3"/><origin xyz="0 0 -0.05"/>'
            '<inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.0005"/></inertial></link>\n'
            f'  <joint name="j{i}" type="revolute"><parent link="{parent}"/><child link="link{i}"/>'
            '<origin xyz="0 0 -0.1"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="18" velocity="20"/>'
            "</joint>"
        )
        parent = f"link{i}"
    (d / "robot.urdf").write_text(f'<?xml version="1.0"?>\n<robot name="can_bench_{n}">\n' + "\n".join(links)
                                  + "\n</robot>\n")
    cfg = {
        "description": "robot.urdf",
        "update_rate": rate,
        "gains": {"default": {"p": 50.0, "d": 0.5}},
        "backends": {
            "can": {
                "interface": interface,
                "channel": channel,
                "bitrate": BITRATE,
                "profile": PROFILE,
                "master_id": MASTER_ID,
                "motors": {f"j{i}": {"id": i, "model": MODEL} for i in range(1, n + 1)},
            }
        },
    }
    path = d / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def set_rate(robot_yaml: Path, rate: float) -> None:
    """Change the update_rate of a generated robot.yaml."""
    cfg = yaml.safe_load(robot_yaml.read_text())
    cfg["update_rate"] = rate
    robot_yaml.write_text(yaml.safe_dump(cfg, sort_keys=False))


# ------------------------------------------------------------------------------ emulator
@contextlib.contextmanager
def emulator(robot_yaml: Path, interface: str, channel: str) -> Iterator[str]:
    """The emulator for ``robot_yaml``: a process on socketcan, a thread on other interfaces. Yields its kind."""
    if interface == "virtual":
        bus = can.Bus(interface="virtual", channel=channel)
        try:
            with MotorEmulator.from_robot(robot_yaml, bus):
                yield "thread in this process"
        finally:
            bus.shutdown()
        return
    with emulator_process(robot_yaml, interface, channel, start_limit=60.0):
        yield "separate process"


# ------------------------------------------------------------------------------ measurements
def _stats(lat: list[float]) -> dict[str, float]:
    if not lat:
        return {"p50_us": math.nan, "p99_us": math.nan, "max_us": math.nan}
    s = sorted(lat)
    return {
        "p50_us": statistics.median(s) * 1e6,
        "p99_us": s[min(len(s) - 1, int(0.99 * len(s)))] * 1e6,
        "max_us": s[-1] * 1e6,
    }


def _command_frames(n: int) -> list[can.Message]:
    data = encode_command(0.0, 0.0, 0.0, 0.0, 0.0, ranges_for(MODEL))  # limp: replies only
    return [can.Message(arbitration_id=i, data=data, is_extended_id=False) for i in range(1, n + 1)]


def _raw_bus(interface: str, channel: str) -> can.BusABC:
    return can.Bus(interface=interface, channel=channel,
                   can_filters=[{"can_id": MASTER_ID, "can_mask": 0x7FF, "extended": False}])


def raw_sync(n: int, interface: str, channel: str, duration: float) -> dict[str, Any]:
    """Blocking python-can round trips: N commands out, N replies in."""
    msgs = _command_frames(n)
    lat: list[float] = []
    timeouts = 0
    with _raw_bus(interface, channel) as bus:
        cpu0 = time.process_time()
        t_start = time.perf_counter()
        end = t_start + duration
        while time.perf_counter() < end:
            t0 = time.perf_counter()
            for m in msgs:
                bus.send(m)
            got: set[int] = set()
            limit = t0 + 0.1
            while len(got) < n:
                msg = bus.recv(max(0.0, limit - time.perf_counter()))
                if msg is None:
                    timeouts += 1
                    break
                got.add(msg.data[0])
            else:
                lat.append(time.perf_counter() - t0)
        elapsed = time.perf_counter() - t_start
        cpu = time.process_time() - cpu0
    return {"round_trips_per_s": len(lat) / elapsed, "timeouts": timeouts, "cpu_percent": 100 * cpu / elapsed,
            **_stats(lat)}


async def _raw_async(n: int, interface: str, channel: str, duration: float) -> dict[str, Any]:
    msgs = _command_frames(n)
    lat: list[float] = []
    timeouts = 0
    got: set[int] = set()
    ev = asyncio.Event()

    def on_frame(msg: can.Message) -> None:
        got.add(msg.data[0])
        if len(got) >= n:
            ev.set()

    with _raw_bus(interface, channel) as bus:
        notifier = can.Notifier(bus, [on_frame], loop=asyncio.get_running_loop())
        try:
            cpu0 = time.process_time()
            t_start = time.perf_counter()
            end = t_start + duration
            while time.perf_counter() < end:
                got.clear()
                ev.clear()
                t0 = time.perf_counter()
                for m in msgs:
                    bus.send(m)
                try:
                    async with asyncio.timeout(0.1):
                        await ev.wait()
                except TimeoutError:
                    timeouts += 1
                    continue
                lat.append(time.perf_counter() - t0)
            elapsed = time.perf_counter() - t_start
            cpu = time.process_time() - cpu0
        finally:
            notifier.stop()
    return {"round_trips_per_s": len(lat) / elapsed, "timeouts": timeouts, "cpu_percent": 100 * cpu / elapsed,
            **_stats(lat)}


def _median_run(runs: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """The run with the median ``key`` (its percentiles stay consistent), plus every run's ``key``."""
    ordered = sorted(runs, key=lambda r: r[key])
    return {**ordered[(len(ordered) - 1) // 2], "runs": [r[key] for r in runs]}


def _missed(ctl: Any) -> tuple[int, int, int]:
    return (sum(s.commands for s in ctl.stats), sum(s.missed for s in ctl.stats), sum(s.late for s in ctl.stats))


async def _backend_free_run(robot_yaml: Path, interface: str, channel: str, duration: float) -> dict[str, Any]:
    """The backend's bus cycle back to back through its public methods (see the module docstring)."""
    config, desc = resolve_robot(robot_yaml)
    joints = apply_overrides(desc, config)
    ctl = load_backend("can").create(config, desc, joints, realtime=True, interface=interface, channel=channel,
                                     max_missed_replies=1000)
    await ctl.open()
    try:
        # hold the measured position with the robot's gains, as the control loop would
        sp = Setpoint(len(joints))
        sp.position[:] = ctl.read()[0]
        sp.kp[:] = [config.gains_for(j.name).p for j in joints]
        sp.kd[:] = [config.gains_for(j.name).d for j in joints]
        view = sp.view
        dt = 0.05
        lat: list[float] = []
        c0, m0, l0 = _missed(ctl)
        cpu0 = time.process_time()
        t_start = time.perf_counter()
        end = t_start + duration
        while time.perf_counter() < end:
            t0 = time.perf_counter()
            ctl.write(view)
            await ctl.step(dt)
            ctl.read()
            lat.append(time.perf_counter() - t0)
        elapsed = time.perf_counter() - t_start
        cpu = time.process_time() - cpu0
        c1, m1, l1 = _missed(ctl)
    finally:
        await ctl.close()
    return {"cycles_per_s": len(lat) / elapsed, "missed_replies": m1 - m0, "late_replies": l1 - l0,
            "motor_cycles": c1 - c0, "cpu_percent": 100 * cpu / elapsed, **_stats(lat)}


async def _backend_realtime(robot_yaml: Path, interface: str, channel: str, duration: float) -> dict[str, Any]:
    """The whole stack at the robot.yaml's update_rate, holding position."""
    async with agentsdk.connect("can", robot=robot_yaml, interface=interface, channel=channel,
                                max_missed_replies=1000) as robot:
        ctl = robot.backend
        await robot.clock.sleep(0.2)  # settle
        ticks0, skipped0 = robot.ticks, robot.missed_deadlines
        c0, m0, l0 = _missed(ctl)
        cpu0 = time.process_time()
        t0 = time.perf_counter()
        await robot.clock.sleep(duration)
        elapsed = time.perf_counter() - t0
        cpu = time.process_time() - cpu0
        c1, m1, l1 = _missed(ctl)
        ticks, skipped = robot.ticks - ticks0, robot.missed_deadlines - skipped0
        state = robot.safety.state.name
    cycles = max(c1 - c0, 1)
    return {
        "update_rate": 1.0 / ctl.period,
        "ticks_per_s": ticks / elapsed,
        "missed_deadlines": skipped,
        "missed_reply_percent": 100 * (m1 - m0) / cycles,
        "late_reply_percent": 100 * (l1 - l0) / cycles,
        "motor_cycles": c1 - c0,
        "cpu_percent": 100 * cpu / elapsed,
        "safety_state": state,
    }


def measure(
    motors: tuple[int, ...] = MOTOR_COUNTS,
    interface: str = "socketcan",
    channel: str = "vcan0",
    duration: float = 1.0,
    rate: float = 2000.0,
    sustain: float = 0.5,
    repeat: int = 3,
    progress: Any = None,
) -> dict[str, Any]:
    """Every measurement for every motor count; returns the JSON-able results."""
    say = progress or (lambda msg: print(msg, file=sys.stderr, flush=True))
    reply_dlc = profile_for(PROFILE).reply_dlc
    rows = []
    with tempfile.TemporaryDirectory(prefix="can-bench-") as tmp:
        for n in motors:
            ch = channel if interface != "virtual" else f"{channel}-{os.getpid()}-{n}"
            robot_yaml = write_robot(Path(tmp), n, rate, interface, ch)
            row: dict[str, Any] = {"motors": n, "wire_limit": wire_limit(n, reply_dlc)}
            with emulator(robot_yaml, interface, ch) as kind:
                row["emulator"] = kind
                runs: dict[str, list[dict[str, Any]]] = {"raw_sync": [], "raw_async": [], "backend_free_run": []}
                for rep in range(repeat):  # interleaved, so that load drifts hit all three alike
                    say(f"can_cycle: {n} motor(s), run {rep + 1}/{repeat}: raw sync, raw async, backend free-run")
                    runs["raw_sync"].append(raw_sync(n, interface, ch, duration))
                    runs["raw_async"].append(asyncio.run(_raw_async(n, interface, ch, duration)))
                    runs["backend_free_run"].append(
                        asyncio.run(_backend_free_run(robot_yaml, interface, ch, duration))
                    )
                row["raw_sync"] = _median_run(runs["raw_sync"], "round_trips_per_s")
                row["raw_async"] = _median_run(runs["raw_async"], "round_trips_per_s")
                row["backend_free_run"] = _median_run(runs["backend_free_run"], "cycles_per_s")
                if sustain > 0:
                    r2 = max(1.0, float(f"{sustain * row['backend_free_run']['cycles_per_s']:.2g}"))
                    set_rate(robot_yaml, r2)
                    say(f"can_cycle: {n} motor(s): backend in realtime at {r2:g} Hz ({sustain:g} x free-run)")
                    row["backend_sustain"] = asyncio.run(_backend_realtime(robot_yaml, interface, ch, duration))
                # last: a rate above what the emulator can answer leaves a backlog of commands in
                # its receive queue that would delay the replies of any later measurement
                set_rate(robot_yaml, rate)
                say(f"can_cycle: {n} motor(s): backend in realtime at {rate:g} Hz")
                row["backend_realtime"] = asyncio.run(_backend_realtime(robot_yaml, interface, ch, duration))
            rows.append(row)
    return {
        "interface": interface,
        "channel": channel,
        "duration_s": duration,
        "profile": PROFILE,
        "reply_dlc": reply_dlc,
        "model": MODEL,
        "bitrate": BITRATE,
        "realtime_rate_hz": rate,
        "sustain_fraction": sustain,
        "repeat": repeat,
        "loadavg": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "cpus": os.cpu_count(),
        "results": rows,
    }


# ------------------------------------------------------------------------------ output
HEADERS = (
    "motors",
    "wire max Hz",
    "raw sync rt/s",
    "raw async rt/s",
    "async p50/p99 µs",
    "backend free-run cyc/s",
    "free-run p50/p99 µs",
    "backend/raw async",
    "realtime ticks/s",
    "rt missed %",
    "rt late %",
    "sustained ticks/s",
    "sus. missed %",
)


def table_rows(res: dict[str, Any]) -> list[list[str]]:
    out = []
    for r in res["results"]:
        w, rs, ra, fr, rt = r["wire_limit"], r["raw_sync"], r["raw_async"], r["backend_free_run"], r["backend_realtime"]
        out.append([
            str(r["motors"]),
            f"{w['hz_worst']:.0f}-{w['hz_best']:.0f}",
            f"{rs['round_trips_per_s']:.0f}",
            f"{ra['round_trips_per_s']:.0f}",
            f"{ra['p50_us']:.0f}/{ra['p99_us']:.0f}",
            f"{fr['cycles_per_s']:.0f}",
            f"{fr['p50_us']:.0f}/{fr['p99_us']:.0f}",
            f"{fr['cycles_per_s'] / ra['round_trips_per_s']:.2f}" if ra["round_trips_per_s"] else "-",
            f"{rt['ticks_per_s']:.0f} of {rt['update_rate']:.0f}",
            f"{rt['missed_reply_percent']:.1f}",
            f"{rt['late_reply_percent']:.1f}",
            *_sustain_cells(r.get("backend_sustain")),
        ])
    return out


def _sustain_cells(su: dict[str, Any] | None) -> list[str]:
    if su is None:
        return ["-", "-"]
    return [f"{su['ticks_per_s']:.0f} of {su['update_rate']:.0f}", f"{su['missed_reply_percent']:.1f}"]


def format_table(res: dict[str, Any]) -> str:
    rows = table_rows(res)
    widths = [max(len(h), *(len(r[k]) for r in rows)) for k, h in enumerate(HEADERS)]
    lines = ["  ".join(h.rjust(widths[k]) for k, h in enumerate(HEADERS)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(c.rjust(widths[k]) for k, c in enumerate(r)) for r in rows]
    return "\n".join(lines)


def _round(x: Any) -> Any:
    if isinstance(x, float):
        return None if not math.isfinite(x) else float(f"{x:.4g}")
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_round(v) for v in x]
    return x


def report(res: dict[str, Any]) -> str:
    head = (f"CAN cycle rates on {res['interface']}:{res['channel']} ({res['model']}, {res['profile']} replies "
            f"DLC {res['reply_dlc']}, {res['duration_s']:g} s per figure, median of {res['repeat']} for the "
            "self-paced loops, emulator: "
            f"{res['results'][0]['emulator'] if res['results'] else '-'}; load avg {res['loadavg']}, "
            f"{res['cpus']} CPU(s))")
    legend = ("wire max = 1 Mbit/s bound for 8-byte command + reply per motor (worst-case stuffing - none); "
              "rt/s = round trips (all N replies) per second; free-run = backend write/step/read back to back; "
              f"realtime = agentsdk.connect at {res['realtime_rate_hz']:g} Hz, missed % of motor-cycles without "
              "a reply by the deadline, late % = replies after it; sustained = the same at "
              f"{res['sustain_fraction']:g} x the free-run rate")
    return "\n".join([head, "", format_table(res), "", legend])


# ------------------------------------------------------------------------------ entry points
def run(quick: bool = False) -> Any:
    """For ``agentsdk bench``: measure on vcan0 if there is one, else on the virtual bus; a Section."""
    interface = "socketcan" if Path("/sys/class/net/vcan0").exists() else "virtual"
    res = measure(interface=interface, duration=0.5 if quick else 1.0, repeat=1 if quick else 3)
    try:
        from agentsdk.bench.common import Comparison, Section, Table
    except ImportError:
        print(report(res))
        return res
    sec = Section("can_cycle", f"CAN cycle rates on {interface} vs raw python-can and the 1 Mbit/s wire limit")
    for r in res["results"]:
        n = r["motors"]
        sec.comparisons.append(Comparison(
            f"{n} motor(s): closed-loop cycles/s, backend free-run", "Hz",
            r["raw_async"]["round_trips_per_s"], r["backend_free_run"]["cycles_per_s"],
            baseline_label="raw python-can async", lower_is_better=False,
            extra={"wire_limit": r["wire_limit"], "raw_sync": r["raw_sync"]},
        ))
        rt = r["backend_realtime"]
        sec.comparisons.append(Comparison(
            f"{n} motor(s): realtime ticks/s at {rt['update_rate']:g} Hz", "Hz", rt["update_rate"], rt["ticks_per_s"],
            baseline_label="requested", lower_is_better=False,
            extra={"missed_reply_percent": rt["missed_reply_percent"], "late_reply_percent": rt["late_reply_percent"]},
        ))
        su = r.get("backend_sustain")
        if su is not None:
            sec.comparisons.append(Comparison(
                f"{n} motor(s): realtime ticks/s at {su['update_rate']:g} Hz (half the free-run rate)", "Hz",
                su["update_rate"], su["ticks_per_s"], baseline_label="requested", lower_is_better=False,
                extra={"missed_reply_percent": su["missed_reply_percent"]},
            ))
    sec.tables.append(Table("per motor count", HEADERS, table_rows(res)))
    sec.notes.append(report(res).split("\n\n")[-1])
    sec.data = _round(res)
    return sec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench/can_cycle.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--interface", default="socketcan", help="socketcan (default; needs CHANNEL) or virtual")
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument("--motors", default=",".join(map(str, MOTOR_COUNTS)), help="motor counts, comma-separated")
    ap.add_argument("--duration", type=float, default=1.0, help="seconds per measurement")
    ap.add_argument("--rate", type=float, default=2000.0, help="update_rate of the realtime run [Hz]")
    ap.add_argument("--sustain", type=float, default=0.5,
                    help="second realtime run at this fraction of the free-running rate (0 = skip)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each self-paced loop; the median is shown")
    ap.add_argument("--quick", action="store_true", help="0.5 s per measurement, one run each")
    ap.add_argument("--json", metavar="PATH", help="also write the JSON to PATH")
    args = ap.parse_args(argv)
    if args.interface == "socketcan" and not Path(f"/sys/class/net/{args.channel}").exists():
        print(f"no {args.channel} here: run inside scripts/run-in-vcan.sh, or use --interface virtual",
              file=sys.stderr)
        return 2
    motors = tuple(int(x) for x in args.motors.split(",") if x.strip())
    res = measure(motors, args.interface, args.channel, 0.5 if args.quick else args.duration, args.rate,
                  args.sustain, 1 if args.quick else args.repeat)
    print(report(res))
    print()
    text = json.dumps(_round(res), indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
