"""Mesh files as the simulators read them: one converted copy per mesh, shared by MuJoCo and PyBullet.

MuJoCo reads binary STL, OBJ and MSH; PyBullet reads STL and OBJ. COLLADA,
PLY, glTF, ... and ASCII STL (which MuJoCo cannot read) are converted once to
binary STL with trimesh into a cache directory, and *both* simulators load the
converted file, so they build their collision hulls from the same vertices.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import threading
from pathlib import Path

__all__ = ["MeshError", "simulator_mesh"]

_NATIVE = {".obj"}
_LOCK = threading.Lock()


class MeshError(Exception):
    """A mesh file that cannot be read or converted."""


def _is_binary_stl(path: Path) -> bool:
    size = path.stat().st_size
    if size < 84:
        return False
    with path.open("rb") as f:
        head = f.read(84)
    count = int.from_bytes(head[80:84], "little")
    return size == 84 + 50 * count


def mesh_cache_dir() -> Path:
    """Where converted meshes are cached (``$AGENTSDK_CACHE_DIR`` or a per-user temp directory)."""
    root = os.environ.get("AGENTSDK_CACHE_DIR")
    user = os.getuid() if hasattr(os, "getuid") else 0
    base = Path(root) if root else Path(tempfile.gettempdir()) / f"agentsdk-meshes-{user}"
    base.mkdir(parents=True, exist_ok=True)
    return base


def simulator_mesh(path: Path) -> Path:
    """The file a simulator should load for mesh ``path`` (``path`` itself, or a cached binary-STL copy).

    Raises :class:`MeshError` when the file cannot be read or has no triangles.
    """
    suffix = path.suffix.lower()
    try:
        if suffix in _NATIVE or (suffix == ".stl" and _is_binary_stl(path)):
            return path
        stat = path.stat()
    except OSError as exc:
        raise MeshError(f"cannot read {path}: {exc}") from exc
    key = f"{path.resolve()}:{stat.st_size}:{stat.st_mtime_ns}"
    digest = hashlib.sha1(key.encode()).hexdigest()[:16]
    out = mesh_cache_dir() / f"{path.stem}-{digest}.stl"
    if out.exists():
        return out
    with _LOCK:
        if out.exists():
            return out
        import trimesh

        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise MeshError(f"cannot read mesh {path}: {exc}") from exc
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise MeshError(f"mesh {path} has no triangles")
        tmp = out.with_suffix(f".{os.getpid()}.tmp")
        mesh.export(tmp, file_type="stl")
        os.replace(tmp, out)
    return out
