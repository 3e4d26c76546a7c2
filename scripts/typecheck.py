"""Run ``mypy --strict`` on the agentsdk package, the backends included.

The repository keeps ``backends/`` beside ``agentsdk/`` and installs it as
``agentsdk.backends`` (``[tool.setuptools.package-dir]``). mypy has no such mapping,
so this script type-checks a temporary tree of symlinks laid out like the installed
package and prints mypy's messages with the repository's paths. Settings are in
``[tool.mypy]`` of pyproject.toml. Exit code: mypy's.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: installed subpackage -> repository folder (as in pyproject's package-dir)
MAPPED = {"backends": "backends", "behaviors": "behaviors", "bench": "bench", "robots": "robots"}


def _farm(tmp: Path) -> Path:
    pkg = tmp / "agentsdk"
    pkg.mkdir()
    for entry in (ROOT / "agentsdk").iterdir():
        if entry.name != "__pycache__":
            (pkg / entry.name).symlink_to(entry)
    for sub, folder in MAPPED.items():
        (pkg / sub).symlink_to(ROOT / folder)
    return pkg


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="agentsdk-typecheck-") as tmp:
        pkg = _farm(Path(tmp))
        cmd = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"), "-p", "agentsdk"]
        env = dict(os.environ, MYPYPATH=tmp)
        proc = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True, check=False)
        out = proc.stdout + proc.stderr
        for sub, folder in MAPPED.items():
            out = out.replace(f"agentsdk/{sub}/", f"{folder}/")
        out = out.replace(str(pkg) + "/", "agentsdk/")
        sys.stdout.write(out)
        return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
