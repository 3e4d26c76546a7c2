"""`agentsdk describe` / `agentsdk check` on bad robot files: one clean error line, non-zero exit, no traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

JOINT = ('<joint name="j" type="revolute"><parent link="base"/><child link="a"/>'
         '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>')


def _files(pkg: Path) -> dict[str, tuple[Path, str]]:
    """name -> (file, a fragment the error must contain)."""
    pkg.mkdir()
    (pkg / "package.xml").write_text("<package><name>pkg</name></package>")
    files = {
        "non_utf8_yaml": (pkg / "robot.yaml", b"description: r.urdf\n\xff\xfe: 1\n", "not UTF-8"),
        "xacro_escape": (
            pkg / "evil.urdf.xacro",
            b'<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
            b'  <link name="x${().__class__.__bases__[0].__subclasses__()}"/>\n</robot>\n',
            "evil.urdf.xacro:2: xacro expression",
        ),
        "huge_mass": (
            pkg / "heavy.urdf",
            ('<robot name="r"><link name="base"/><link name="a"><inertial><mass value="1e308"/>'
             f'<inertia ixx="1" iyy="1" izz="1"/></inertial></link>{JOINT}</robot>').encode(),
            "link 'a': mass 1e+308 kg is not physical",
        ),
        "inf_inertia": (
            pkg / "inf.urdf",
            ('<robot name="r"><link name="base"/><link name="a"><inertial><mass value="1"/>'
             f'<inertia ixx="inf" iyy="1" izz="1"/></inertial></link>{JOINT}</robot>').encode(),
            "must be finite",
        ),
        "truncated": (pkg / "cut.urdf", f'<robot name="r"><link name="base"/>{JOINT[:40]}'.encode(), "malformed XML"),
        "long_description": (pkg / "long.yaml", ("description: " + "x" * 5000 + ".urdf\n").encode(), "long.yaml"),
    }
    out = {}
    for name, (path, data, fragment) in files.items():
        path.write_bytes(data)
        out[name] = (path, fragment)
    return out


@pytest.mark.timeout(300)
@pytest.mark.parametrize("command", ["describe", "check"])
def test_cli_reports_bad_files_in_one_line(tmp_path: Path, command: str) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    for name, (path, fragment) in _files(tmp_path / "pkg").items():
        proc = subprocess.run(
            [sys.executable, "-m", "agentsdk", command, str(path)],
            capture_output=True, text=True, env=env, cwd=tmp_path, timeout=240, check=False,
        )
        assert proc.returncode != 0, f"{name}: exit status 0\n{proc.stdout}\n{proc.stderr}"
        assert "Traceback" not in proc.stderr + proc.stdout, f"{name}:\n{proc.stderr}"
        errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1, f"{name}: {proc.stderr}"
        assert fragment in errors[0], f"{name}: {errors[0]}"
