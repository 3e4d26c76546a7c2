"""Issue 27 acceptance 4: from a fresh clone, every CLI command of the README as a new user types it.

The commands come from README.md itself (every fenced shell/text block; a line that starts with ``agentsdk``
or ``python3 -m agentsdk``, its comment dropped): ``[--opt a|b]`` runs once without the option and once per
alternative, ``[--flag]`` once without and once with every such flag. They run in order, in a clone of the
committed tree (``git clone``: only what a user gets), with that clone first on ``PYTHONPATH`` (the package
itself is installed by ``scripts/test.sh``, so ``pip install -e .`` is not repeated here). Each must:

* exit 0, or end with an error line that names what to do;
* print no traceback and no C-level chatter (simulator banners, GL/EGL warnings);
* print no raw JSON on stdout unless the command asked for it (``--json``).

Placeholders become real files (``my_robot.urdf``: a URDF of the repository; ``path/to/scene.xml``: an MJCF
model). Commands that serve until Ctrl-C (``serve``, ``emulate-can`` on a host with CAN) get SIGINT once they
are up. Skipped, with the reason in the test id: commands that need hardware or root (``--backend can``,
``can:`` endpoints, ``--rt-priority``, ``vcan``), the page's ``--web-wait`` (someone must press Start:
tests/test_webview.py does), and the full ``bench`` (minutes; ``bench --quick`` runs).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from ros_domains import random_domain

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

pytestmark = [pytest.mark.slow]

#: placeholder -> a real file of the repository (relative to the clone)
PLACEHOLDERS = {
    "my_robot.urdf": "tests/fixtures/sensor_arm/sensor_arm.urdf",
    "path/to/robot.urdf": "tests/fixtures/sensor_arm/sensor_arm.urdf",
    "path/to/scene.xml": "tests/fixtures/mjcf_arm/arm.xml",
    "path/to/robot.yaml": "robots/arm3/robot.yaml",
    "my_behavior.py": "behaviors/wave.py",
}
#: output of C libraries that must not reach the user
C_NOISE = re.compile(r"pybullet build time|b3Printf|libEGL|MESA[-_:]|GLFW|ALSA lib|Fontconfig|argv\[0\]|"
                     r"^Warning: |XDG_RUNTIME_DIR|swrast|glx", re.M)
#: an error that says what to do: an instruction, a command or an option to use
HINT = re.compile(r"\b(install|run|use|choose|pass|add|set|check|see|try|give|plug|remove|rename|fix|start|"
                  r"open|call|leave|move|lower|raise|increase|reduce)\b|agentsdk \w+|--\w", re.I)
LONG_RUNNING = ("serve", "emulate-can")


def _readme_lines() -> list[str]:
    lines = []
    for m in re.finditer(r"```(\w*)\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S):
        if m.group(1) not in ("", "bash", "sh", "shell", "text", "console"):
            continue
        if "run-in-vcan.sh" in m.group(2):  # a script for the vcan VM (tests/test_readme.py checks it)
            continue
        for line in m.group(2).splitlines():
            text = line.strip()
            if re.match(r"(python3 -m pip install .*&& )?(python3 -m )?agentsdk\b", text):
                lines.append(text)
    return lines


def _variants(line: str) -> list[str]:
    """The command lines one README line stands for (see the module documentation)."""
    line = re.sub(r"^python3 -m pip install .*? && ", "", line)  # the install: done by scripts/test.sh
    line = re.sub(r"\s+#.*$", "", line)  # the comment
    line = re.sub(r"^python3 -m agentsdk\b", "agentsdk", line)
    groups = re.findall(r"\[([^\]]+)\]", line)

    def pick(choice: dict[int, str]) -> str:  # each optional group in place: its chosen text, or nothing
        it = iter(range(len(groups)))
        text = re.sub(r"\[([^\]]+)\]", lambda m: choice.get(next(it), ""), line)
        return " ".join(text.split())

    out = [pick({})]
    flags = [i for i, g in enumerate(groups) if "|" not in g]
    out += [pick({i: groups[i]}) for i in flags]
    if len(flags) > 1:
        out.append(pick({i: groups[i] for i in flags}))
    for i, g in enumerate(groups):
        if "|" in g:
            opt, _, alts = g.rpartition(" ")
            out += [pick({i: f"{opt} {alt}"}) for alt in alts.split("|")]
    return out


def _skip_reason(cmd: str) -> str:
    if "--backend can" in cmd or re.search(r"\bcan:", cmd) or "--rt-priority" in cmd:
        return "needs a CAN bus with motors and real-time privileges (hardware)"
    if "--backend ros2" in cmd:
        return "drives a robot served by another process (tests/test_ros2_backend.py runs it against agentsdk serve)"
    if cmd.startswith("agentsdk vcan"):
        return "needs root and user-mode Linux (scripts/test.sh runs the vcan suite)"
    if "--web-wait" in cmd:
        return "waits for someone to press Start in the page (tests/test_webview.py does)"
    if cmd.split()[:2] == ["agentsdk", "bench"] and "--quick" not in cmd and "--only" not in cmd:
        return "the full benchmark takes minutes (bench --quick runs)"
    return ""


COMMANDS = list(dict.fromkeys(c for line in _readme_lines() for c in _variants(line)))


def test_the_readme_has_its_commands() -> None:
    names = {c.split()[1] for c in COMMANDS}
    assert {"run", "teleop", "robots", "describe", "check", "graph", "bench", "serve", "replay"} <= names, names


@pytest.fixture(scope="module")
def clone(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A fresh clone of the committed tree."""
    dest = tmp_path_factory.mktemp("clone") / "agentsdk"
    subprocess.run(["git", "clone", "--quiet", "--no-hardlinks", str(ROOT), str(dest)], check=True, timeout=300,
                   capture_output=True)
    yield dest


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _prepare(cmd: str) -> list[str]:
    for placeholder, real in PLACEHOLDERS.items():
        cmd = cmd.replace(placeholder, real)
    argv = shlex.split(cmd)[1:]
    if "--web" in argv:  # another test may hold 8080
        if "--port" in argv:
            argv[argv.index("--port") + 1] = str(_free_port())
        else:
            argv += ["--port", str(_free_port())]
    if argv[0] == "serve":  # a domain of its own: the other tests' DDS participants are not disturbed
        domain = str(random_domain())
        if "--domain-id" in argv:
            argv[argv.index("--domain-id") + 1] = domain
        else:
            argv += ["--domain-id", domain]
    return argv


def _run_until_up(argv: list[str], cwd: Path, env: dict[str, str]) -> tuple[int, str, str]:
    """A command that serves until Ctrl-C: SIGINT once it says so (or it ends by itself).

    Both pipes are drained by threads of their own until EOF and nothing else reads them: a
    ``communicate()`` here would read (and close) stderr under the reader thread, which then fails
    with "I/O operation on closed file" when the machine is slow enough to lose that race.
    """
    import threading

    proc = subprocess.Popen([sys.executable, "-m", "agentsdk", *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stderr is not None
    deadline = time.monotonic() + 180
    out: list[str] = []
    err: list[str] = []
    readers = [threading.Thread(target=lambda f=f, into=into: into.extend(iter(f.readline, "")), daemon=True)
               for f, into in ((proc.stdout, out), (proc.stderr, err))]
    for reader in readers:
        reader.start()
    try:
        while proc.poll() is None and time.monotonic() < deadline and not any("Ctrl-C" in x for x in err):
            time.sleep(0.1)
        if proc.poll() is None:
            time.sleep(1.0)
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        for reader in readers:  # EOF follows the exit, unless a child of the command still holds the pipe
            reader.join(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if not any(r.is_alive() for r in readers):  # never close a pipe under a thread still reading it
            proc.stdout.close()
            proc.stderr.close()
    code = proc.returncode
    return (0 if code == 130 else code), "".join(out), "".join(err)


@pytest.mark.timeout(900)
@pytest.mark.parametrize("cmd", COMMANDS)
def test_readme_command(cmd: str, clone: Path) -> None:
    reason = _skip_reason(cmd)
    if reason:
        pytest.skip(reason)
    argv = _prepare(cmd)
    env = {**os.environ, "PYTHONPATH": str(clone)}
    env.pop("DISPLAY", None)
    if argv[0] in LONG_RUNNING:
        code, out, err = _run_until_up(argv, clone, env)
    else:
        proc = subprocess.run([sys.executable, "-m", "agentsdk", *argv], cwd=clone, env=env, capture_output=True,
                              text=True, timeout=840, check=False)
        code, out, err = proc.returncode, proc.stdout, proc.stderr
    both = out + err
    shown = f"$ agentsdk {shlex.join(argv)}\n--- exit {code}; stdout:\n{out[-4000:]}\n--- stderr:\n{err[-4000:]}"
    assert "Traceback" not in both, shown
    assert not C_NOISE.search(both), shown
    if "--json" not in argv:
        for line in out.splitlines():
            if line.lstrip().startswith(("{", "[")):
                with pytest.raises(ValueError):  # a line like "[1/3] ..." is fine; a JSON document is not
                    json.loads(line)
    if code != 0:  # the error is the last thing said, and it says what to do
        said = [x for x in err.splitlines() if x.strip()]
        assert said, shown
        assert HINT.search(said[-1]), f"the error does not say what to do:\n{shown}"
