"""Random URDFs on both simulators, each load in a worker process: a process never dies.

Hypothesis writes small robots the way real exporters do - random trees, links
and joints in any order, degenerate inertias (missing, zero, negative,
violating A + B >= C), odd geometry (zero-size shapes, capsules, meshes that
are missing or fine), placeholder limits, mimic joints - every one a file
urdfdom accepts. Each loads on MuJoCo and on PyBullet in a long-lived worker
(:class:`agentsdk.probe.ProbePool`); the property: no worker ever dies, every
file loads on both, and both report the same joints, limits, masses and
self-collision pairs. ``AGENTSDK_RANDOM_URDF_EXAMPLES`` raises the example count.
"""

from __future__ import annotations

import itertools
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agentsdk.probe import ProbePool

pytestmark = pytest.mark.slow

MESH = (Path(__file__).parent / "fixtures" / "mesh_pkg" / "meshes" / "link.stl").resolve()
EXAMPLES = int(os.environ.get("AGENTSDK_RANDOM_URDF_EXAMPLES", "25"))
_counter = itertools.count()

num = st.floats(min_value=-0.3, max_value=0.3, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(num, num, num)
positive = st.floats(min_value=1e-3, max_value=0.2)


@st.composite
def inertial(draw: st.DrawFn) -> str:
    kind = draw(st.sampled_from(["none", "normal", "zero_mass", "zero_inertia", "negative", "triangle", "full"]))
    if kind == "none":
        return ""
    mass = {"zero_mass": 0.0}.get(kind, draw(st.floats(min_value=0.01, max_value=3.0)))
    i = draw(st.floats(min_value=1e-5, max_value=0.05))
    ixx, iyy, izz, ixy, ixz, iyz = i, i, i, 0.0, 0.0, 0.0
    if kind in ("zero_mass", "zero_inertia"):
        ixx = iyy = izz = 0.0
    elif kind == "negative":
        ixx = -i / 2
    elif kind == "triangle":
        izz = 5 * i
    elif kind == "full":
        ixy, ixz, iyz = draw(st.tuples(*(st.floats(min_value=-i, max_value=i) for _ in range(3))))
    xyz = " ".join(f"{v:.4g}" for v in draw(vec3))
    return (
        f'<inertial><origin xyz="{xyz}" rpy="{" ".join(f"{v:.4g}" for v in draw(vec3))}"/><mass value="{mass:.6g}"/>'
        f'<inertia ixx="{ixx:.6g}" iyy="{iyy:.6g}" izz="{izz:.6g}" ixy="{ixy:.6g}" ixz="{ixz:.6g}" iyz="{iyz:.6g}"/>'
        "</inertial>"
    )


@st.composite
def geometry(draw: st.DrawFn) -> str:
    kind = draw(st.sampled_from(["box", "sphere", "cylinder", "capsule", "mesh", "zero_box", "zero_sphere",
                                 "missing_mesh", "scaled_mesh"]))
    shape = {
        "box": lambda: f'<box size="{draw(positive):.4g} {draw(positive):.4g} {draw(positive):.4g}"/>',
        "sphere": lambda: f'<sphere radius="{draw(positive):.4g}"/>',
        "cylinder": lambda: f'<cylinder radius="{draw(positive):.4g}" length="{draw(positive):.4g}"/>',
        "capsule": lambda: f'<capsule radius="{draw(positive):.4g}" length="{draw(positive):.4g}"/>',
        "mesh": lambda: f'<mesh filename="file://{MESH}"/>',
        "scaled_mesh": lambda: f'<mesh filename="{MESH}" scale="{draw(positive) * 5:.4g} 1 -1"/>',
        "zero_box": lambda: '<box size="0 0.1 0.1"/>',
        "zero_sphere": lambda: '<sphere radius="0"/>',
        "missing_mesh": lambda: '<mesh filename="package://nowhere/meshes/gone.stl"/>',
    }[kind]()
    tag = draw(st.sampled_from(["collision", "visual"]))
    xyz = " ".join(f"{v:.4g}" for v in draw(vec3))
    return f'<{tag}><origin xyz="{xyz}"/><geometry>{shape}</geometry></{tag}>'


@st.composite
def limit(draw: st.DrawFn, jtype: str) -> str:
    kind = draw(st.sampled_from(["normal", "placeholder", "zero_effort", "swapped", "no_range", "absent"]))
    if jtype == "continuous" and kind == "absent":
        return ""
    if kind == "placeholder":
        return '<limit lower="0" upper="0" effort="0" velocity="0"/>'
    if kind == "no_range":
        return '<limit effort="5" velocity="1"/>'
    lo = draw(st.floats(min_value=-2.0, max_value=0.0))
    hi = draw(st.floats(min_value=0.1, max_value=2.0))
    if kind == "swapped":
        lo, hi = hi, lo
    effort = 0.0 if kind == "zero_effort" else draw(st.floats(min_value=0.5, max_value=50.0))
    return f'<limit lower="{lo:.4g}" upper="{hi:.4g}" effort="{effort:.4g}" velocity="{draw(positive) * 10:.4g}"/>'


@st.composite
def robots(draw: st.DrawFn) -> str:
    n = draw(st.integers(min_value=2, max_value=6))
    names = [f"link_{i}" for i in range(n)]
    parents = [None] + [draw(st.integers(min_value=0, max_value=i - 1)) for i in range(1, n)]
    links = []
    for name in names:
        shapes = "".join(draw(st.lists(geometry(), max_size=2)))
        links.append(f'<link name="{name}">{draw(inertial())}{shapes}</link>')
    joints = []
    movable: list[str] = []
    for i in range(1, n):
        jtype = draw(st.sampled_from(["revolute", "continuous", "prismatic", "fixed", "floating"]))
        jname = f"joint_{i}"
        axis = draw(st.sampled_from(["1 0 0", "0 1 0", "0 0 1", "0 0.6 0.8", "-1 0 0"]))
        xyz, rpy = (" ".join(f"{v:.4g}" for v in draw(vec3)) for _ in range(2))
        body = [
            f'<parent link="{names[parents[i]]}"/><child link="{names[i]}"/>',  # type: ignore[index]
            f'<origin xyz="{xyz}" rpy="{rpy}"/>',
        ]
        if jtype in ("revolute", "continuous", "prismatic"):
            body.append(f'<axis xyz="{axis}"/>')
            if jtype == "continuous":
                body.append(draw(limit("continuous")))
            else:
                text = draw(limit(jtype))
                body.append(text or '<limit lower="-1" upper="1" effort="5" velocity="1"/>')
            if movable and draw(st.booleans()):
                leader = draw(st.sampled_from([*movable, "no_such_joint"]))
                body.append(f'<mimic joint="{leader}" multiplier="{draw(num) * 3:.3g}" offset="{draw(num):.3g}"/>')
            if draw(st.booleans()):
                body.append(f'<dynamics damping="{draw(positive):.3g}" friction="{draw(positive) / 10:.3g}"/>')
            movable.append(jname)
        joints.append(f'<joint name="{jname}" type="{jtype}">{"".join(body)}</joint>')
    elements = links + joints
    order = draw(st.permutations(range(len(elements))))
    return '<?xml version="1.0"?>\n<robot name="random">\n' + "\n".join(elements[k] for k in order) + "\n</robot>\n"


@pytest.fixture(scope="module")
def pool() -> Iterator[ProbePool]:
    # the random robots use a fixture mesh by absolute path: a robot file reaches only files inside its
    # package roots, so the mesh's package is put on the package path (a root)
    env = {"AGENTSDK_PACKAGE_PATH": os.pathsep.join(filter(None, [str(MESH.parents[1]),
                                                                 os.environ.get("AGENTSDK_PACKAGE_PATH")]))}
    with ProbePool(workers=2, timeout=120, env=env) as workers:
        yield workers


@pytest.fixture(scope="module")
def workdir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="agentsdk-random-urdf-") as tmp:
        yield Path(tmp)


def _same(a: Any, b: Any) -> bool:
    fa, fb = float(a), float(b)
    return fa == fb if math.isinf(fa) or math.isinf(fb) else math.isclose(fa, fb, rel_tol=1e-9, abs_tol=1e-12)


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=os.environ.get("AGENTSDK_RANDOM_URDF_SEED") is None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(text=robots())
def test_random_urdfs_load_on_both_simulators_and_never_kill_a_process(
    text: str, pool: ProbePool, workdir: Path
) -> None:
    path = workdir / f"random_{next(_counter)}.urdf"
    path.write_text(text)
    mj, pb = pool.run([{"robot": str(path), "backend": b, "duration": 0.02} for b in ("mujoco", "pybullet")])
    for backend, r in (("mujoco", mj), ("pybullet", pb)):
        assert not r.get("died"), f"{backend} worker died on:\n{text}\n{r['error']}"
        assert not r.get("unexpected"), f"{backend}: {r['error_type']}: {r['error']}\n{text}"
        assert r["loaded"], f"{backend}: {r['error_type']}: {r['error']}\n{text}"
    assert mj["joints"] == pb["joints"], text
    a, b = mj["report"], pb["report"]
    assert [j[0] for j in a["joints"]] == [j[0] for j in b["joints"]], text
    for ja, jb in zip(a["joints"], b["joints"], strict=True):
        assert all(_same(x, y) for x, y in zip(ja[1:], jb[1:], strict=True)), (ja, jb, text)
    for link, mass in a["masses"].items():
        assert _same(mass, b["masses"].get(link, 0.0)), (link, text)
    assert a["pairs"] == b["pairs"], text
