"""The MIT motor emulator as a separate process, for the CAN benchmarks (``can_cycle``, ``can_host_cost``).

Real motors are other hardware: on socketcan the benchmarks run the emulator
(``python -m agentsdk.backends.can.emulator``) in its own process, always from this checkout, and
stop it however the measurement ends.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

__all__ = ["READY", "emulator_process"]

ROOT = Path(__file__).resolve().parents[1]
#: the emulator's log line once it answers frames ("emulating <robot> on <interface>:<channel> ...")
READY = "emulating "


@contextlib.contextmanager
def emulator_process(
    robot_yaml: str | Path,
    interface: str = "socketcan",
    channel: str = "vcan0",
    *,
    realtime: bool = False,
    args: Sequence[str] = (),
    start_limit: float = 120.0,
) -> Iterator[subprocess.Popen[bytes]]:
    """Run the emulator for ``robot_yaml`` on ``interface:channel`` until the block ends; yields the process.

    ``realtime``: at a real-time priority (``chrt --fifo 10``) where permitted (root and ``chrt``),
    as the vcan test suite runs it: the replies do not wait for the host's CPU. ``args``: more
    ``emulate-can`` options. Raises RuntimeError with the emulator's output when it does not
    report ready within ``start_limit`` seconds (or exits first).
    """
    rt = ["chrt", "--fifo", "10"] if realtime and os.geteuid() == 0 and shutil.which("chrt") else []
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT)  # this checkout's emulator, whichever checkout the host under test is
    env.pop("PYTHONSTARTUP", None)
    fd, name = tempfile.mkstemp(prefix="can-bench-emulator-", suffix=".log")
    log = Path(name)
    with os.fdopen(fd, "wb") as out:
        proc = subprocess.Popen(
            [*rt, sys.executable, "-m", "agentsdk.backends.can.emulator", "--robot", str(robot_yaml),
             "--interface", interface, "--channel", channel, "--log-level", "INFO", *args],
            stdout=out, stderr=subprocess.STDOUT, env=env, cwd=ROOT,
        )
    try:
        deadline = time.monotonic() + start_limit
        while READY not in log.read_text(errors="replace"):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"emulator did not start:\n{log.read_text(errors='replace')}")
            time.sleep(0.02)
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.unlink(missing_ok=True)
