"""Every bad robot file ends in the error hierarchy (issue 20 item 7).

A seeded fuzz over mutated URDF, xacro, MJCF and robot.yaml files (truncated, non-UTF-8,
huge numbers, 1e308, inf, NaN, cycles, duplicate names, missing attributes, deep nesting,
long paths, hostile expressions): each case loads cleanly or raises an ``AgentSDKError``
subclass with a message; nothing else. Bounds: each xacro expansion stops at
``XACRO_TIME_LIMIT`` (here 10 s) and the whole test at its pytest timeout; a sample of the
loaded cases is compiled by MuJoCo in worker processes (no process death).

``AGENTSDK_FUZZ_SEED`` picks another seed, ``AGENTSDK_FUZZ_CASES`` another count.
"""

from __future__ import annotations

import logging
import os
import random
import re
import shutil
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest

from agentsdk.description import apply_overrides, resolve_robot, xacro_expand
from agentsdk.errors import AgentSDKError
from agentsdk.probe import ProbePool
from agentsdk.registry import load_backend

ROOT = Path(__file__).resolve().parents[1]
ROBOTS = ROOT / "robots"
FIXTURES = Path(__file__).resolve().parent / "fixtures"
SEED = int(os.environ.get("AGENTSDK_FUZZ_SEED", "20"))
CASES = int(os.environ.get("AGENTSDK_FUZZ_CASES", "520"))

EXTREMES = ["1e308", "-1e308", "1e309", "inf", "-inf", "nan", "NaN", "1e-320", "0", "-0", "-5", "9" * 400,
            "1e30", "0x10", "1_000", "", " ", "1 2", "abc"]
HOSTILE = ["${1/0}", "${undefined}", "${9**9**8}", "${'a'*10**10}", "$(arg nope)", "${python.vars(python)}",
           "${().__class__}", "$(eval ().__class__)", "${", "$(", "${[]", "${xacro.load_yaml('/etc/passwd')}",
           "$(find no_such_package)", "${math.factorial(10**5) % 7}", "${python.type(1)}"]


@dataclass
class Case:
    index: int
    kind: str  # urdf, xacro, mjcf, yaml
    mutation: str
    path: Path


def _numbers(text: str) -> list[re.Match[str]]:
    return list(re.finditer(r"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE]-?\d+)?", text))


def _mutate(rng: random.Random, kind: str, text: str, name: str) -> tuple[str, bytes]:
    """One mutation of ``text``: its name and the resulting bytes."""
    generic = ["truncate", "non_utf8", "number", "inertial", "drop_attr", "duplicate", "cycle", "long_path",
               "deep_nesting", "flip_bytes", "garbage", "limits", "empty"]
    special = {"xacro": ["hostile", "recursive_macro", "self_include", "self_property"],
               "yaml": ["yaml_value", "yaml_nesting", "yaml_description"],
               "mjcf": ["mjcf_include", "hostile_attr"],
               "urdf": ["hostile_attr"]}[kind]
    mutation = rng.choice(generic + special * 2)
    data = text
    if mutation == "truncate":
        return mutation, text.encode()[: rng.randrange(len(text))]
    if mutation == "non_utf8":
        raw = text.encode()
        at = rng.randrange(len(raw))
        return mutation, raw[:at] + rng.choice([b"\xff\xfe", b"\x80", b"\xc3\x28", b"\xed\xa0\x80"]) + raw[at:]
    if mutation == "flip_bytes":
        raw = bytearray(text.encode())
        for _ in range(rng.randint(1, 6)):
            raw[rng.randrange(len(raw))] = rng.randrange(256)
        return mutation, bytes(raw)
    if mutation == "empty":
        return mutation, rng.choice([b"", b" ", b"\n", b"<robot/>", b"<mujoco/>", b"---\n", b"null\n"])
    if mutation == "number":
        found = _numbers(text)
        for m in rng.sample(found, min(len(found), rng.randint(1, 4))):
            data = data[: m.start()] + rng.choice(EXTREMES) + data[m.end():] if len(data) == len(text) else data
        if data == text and found:
            m = rng.choice(found)
            data = text[: m.start()] + rng.choice(EXTREMES) + text[m.end():]
        return mutation, data.encode()
    if mutation == "inertial":
        value = rng.choice(["1e308", "inf", "nan", "-1", "1e-300", "1e300", "0"])
        pattern = r'((?:mass|value|ixx|iyy|izz|ixy|ixz|iyz|diaginertia|inertia|m1|m2|ee_m)\s*[=:]\s*"?)[^"\s,}]+'
        data = re.sub(pattern, lambda m: m.group(1) + value, text, count=rng.randint(1, 6))
        return f"{mutation}={value}", data.encode()
    if mutation == "limits":
        attr = rng.choice(["lower", "upper", "effort", "velocity", "range", "p", "d", "max_velocity"])
        value = rng.choice(["-5", "1e308", "nan", "inf", "-inf", "0", "5", "-1e308"])
        data = re.sub(rf'(\b{attr}\s*[=:]\s*"?)[^"\s,}}]+', lambda m: m.group(1) + value, text, count=2)
        return f"{mutation}:{attr}={value}", data.encode()
    if mutation == "drop_attr":
        attrs = list(re.finditer(r'\s[\w:]+="[^"]*"', text))
        for m in sorted(rng.sample(attrs, min(len(attrs), rng.randint(1, 3))), key=lambda m: -m.start()):
            data = data[: m.start()] + data[m.end():]
        return mutation, data.encode()
    if mutation == "duplicate":
        blocks = list(re.finditer(r"<(link|joint|body|geom|xacro:property)\b.*?(?:/>|</\1>)", text, re.S))
        if blocks:
            m = rng.choice(blocks)
            data = text[: m.end()] + m.group(0) + text[m.end():]
        return mutation, data.encode()
    if mutation == "cycle":
        parents = list(re.finditer(r'<parent link="([^"]+)"/>\s*<child link="([^"]+)"/>', text))
        if parents:
            m = rng.choice(parents)
            data = text[: m.start()] + f'<parent link="{m.group(2)}"/><child link="{m.group(1)}"/>' + text[m.end():]
        else:
            data = text.replace("<body", '<body name="dup"', 1)
        return mutation, data.encode()
    if mutation == "long_path":
        long_name = rng.choice(["a" * 300 + ".stl", "d/" * 3000 + "x.stl", "package://" + "p" * 400 + "/m.stl",
                                "x" * 5000 + ".urdf", "../" * 200 + "etc/passwd", "/dev/zero.stl", "\x00.stl"])
        if kind == "yaml":
            data = re.sub(r"description: .*", f"description: {long_name}", text)
        elif kind == "mjcf":
            data = text.replace("<worldbody>", f'<asset><mesh name="lp" file="{long_name}"/></asset><worldbody>', 1)
        else:
            data = re.sub(r"(<link name=\"[^\"]+\">)", lambda m: m.group(1) + "<visual><geometry><mesh filename="
                          f'"{long_name}"/></geometry></visual>', text, count=1)
        return f"{mutation}:{long_name[:12]}", data.encode()
    if mutation == "deep_nesting":
        depth = rng.choice([300, 3000, 30000])
        if kind == "yaml":
            return f"{mutation}:{depth}", (text + "\nextra: " + "[" * depth + "]" * depth + "\n").encode()
        inner = "<a>" * depth + "</a>" * depth
        data = re.sub(r"(<(?:robot|mujoco)\b[^>]*>)", lambda m: m.group(1) + inner, text, count=1)
        return f"{mutation}:{depth}", data.encode()
    if mutation == "garbage":
        at = rng.randrange(len(text))
        return mutation, (text[:at] + rng.choice(["<", "&", '"', "]]>", "&lol;", "<!DOCTYPE x>", "\x00"]) +
                          text[at:]).encode()
    if mutation == "hostile":
        payload = rng.choice(HOSTILE)
        attrs = list(re.finditer(r'="([^"]*)"', text))
        m = rng.choice(attrs)
        return f"{mutation}:{payload}", (text[: m.start()] + f'="{payload}"' + text[m.end():]).encode()
    if mutation == "hostile_attr":
        attrs = list(re.finditer(r'="([^"]*)"', text))
        m = rng.choice(attrs)
        value = rng.choice(["${1}", "$(find x)", "&amp;", "1e308 1e308 1e308", "nan nan nan", "-1 -1 -1"])
        return f"{mutation}:{value}", (text[: m.start()] + f'="{value}"' + text[m.end():]).encode()
    if mutation == "recursive_macro":
        data = text.replace("</robot>", '<xacro:macro name="loop" params=""><xacro:loop/></xacro:macro>'
                            "<xacro:loop/></robot>")
        return mutation, data.encode()
    if mutation == "self_include":
        data = text.replace("</robot>", f'<xacro:include filename="{name}"/></robot>')
        return mutation, data.encode()
    if mutation == "self_property":
        data = text.replace("</robot>", '<xacro:property name="pp" value="${pp}"/><link name="${pp}"/></robot>')
        return mutation, data.encode()
    if mutation == "yaml_value":
        key = rng.choice(["update_rate", "gains", "joint_limits", "initial_positions", "safety", "backends",
                          "strict", "xacro_args", "model_gains", "description", "name", "trusted", "srdf"])
        value = rng.choice([".nan", ".inf", "-.inf", "1e308", "-1", "[]", "{}", "null", "'x'", "{a: {b: .nan}}",
                            "{joint1: {p: 1e308, d: .inf}}", "{default: {max_velocity: -1}}",
                            "!!python/object:os.system x"])
        if re.search(rf"^{key}:", text, re.M):
            data = re.sub(rf"^{key}:.*$", f"{key}: {value}", text, count=1, flags=re.M)
        else:
            data = text + f"\n{key}: {value}\n"
        return f"{mutation}:{key}={value}", data.encode()
    if mutation == "yaml_nesting":
        return mutation, ("a: &a [" + ",".join(["*a"] * 0) + "1]\n" + text + "\nx: " + "{a: " * 2000 + "1"
                          + "}" * 2000 + "\n").encode()
    if mutation == "yaml_description":
        target = rng.choice(["/etc/passwd", "robot.yaml", "/dev/null", ".", "missing.urdf", "/proc/self/mem",
                             "arm3.urdf.xacro\x00", "\xff.urdf"])
        return f"{mutation}:{target[:10]}", re.sub(r"description: .*", f"description: {target!r}", text).encode()
    if mutation == "mjcf_include":
        target = rng.choice(["/etc/passwd", "arm.xml", "nope.xml", "/dev/zero"])
        data = text.replace("<worldbody>", f'<include file="{target}"/><worldbody>', 1)
        return f"{mutation}:{target}", data.encode()
    raise AssertionError(mutation)  # pragma: no cover


def _seeds(base: Path) -> dict[str, tuple[Path, Path, str]]:
    """kind -> (directory to copy the case into, the file name the case takes, seed text)."""
    robots = base / "robots"
    shutil.copytree(ROBOTS / "arm3", robots / "arm3")
    shutil.copytree(ROBOTS / "common", robots / "common")
    shutil.copy(ROBOTS / "package.xml", robots)
    mesh_pkg = base / "mesh_pkg"
    shutil.copytree(FIXTURES / "mesh_pkg", mesh_pkg)
    mjcf = base / "mjcf"
    shutil.copytree(FIXTURES / "mjcf_arm", mjcf)
    return {
        "urdf": (mesh_pkg / "urdf", mesh_pkg / "urdf", (mesh_pkg / "urdf" / "mesh_arm.urdf").read_text()),
        "xacro": (robots / "arm3", robots / "arm3", (robots / "arm3" / "arm3.urdf.xacro").read_text()),
        "mjcf": (mjcf, mjcf, (mjcf / "arm.xml").read_text()),
        "yaml": (robots / "arm3", robots / "arm3", (robots / "arm3" / "robot.yaml").read_text()),
    }


def _cases(base: Path) -> Iterator[Case]:
    rng = random.Random(SEED)
    seeds = _seeds(base)
    suffix = {"urdf": ".urdf", "xacro": ".urdf.xacro", "mjcf": ".xml", "yaml": ".yaml"}
    # xacro cases cost a worker process each: fewer of them
    kinds = ["urdf"] * 4 + ["xacro"] * 2 + ["mjcf"] * 3 + ["yaml"] * 3
    for index in range(CASES):
        kind = rng.choice(kinds)
        directory, _, text = seeds[kind]
        name = f"case{index}{suffix[kind]}"
        mutation, data = _mutate(rng, kind, text, name)
        path = directory / name
        path.write_bytes(data)
        yield Case(index, kind, mutation, path)


def _load(case: Case) -> str:
    """Load the case as `connect` does, up to the backend's start (mock); 'loaded' or the error's type."""
    try:
        config, description = resolve_robot(case.path)
        joints = apply_overrides(description, config)
        backend = load_backend("mock").create(config, description, joints, realtime=False)
        backend.servo_gains  # noqa: B018 - the model gains, computed when a backend starts
    except AgentSDKError as exc:
        assert str(exc).strip(), f"case {case.index} ({case.kind}, {case.mutation}): an empty message"
        return type(exc).__name__
    return "loaded"


@pytest.fixture
def quiet() -> Iterator[None]:
    logger = logging.getLogger("agentsdk")
    level = logger.level
    logger.setLevel(logging.ERROR)  # hundreds of repair warnings
    try:
        yield
    finally:
        logger.setLevel(level)


@pytest.mark.timeout(600)
@pytest.mark.filterwarnings("ignore")
def test_mutated_robot_files_load_or_raise_an_agentsdk_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, quiet: None
) -> None:
    monkeypatch.setattr(xacro_expand, "XACRO_TIME_LIMIT", 10.0)
    monkeypatch.setenv("AGENTSDK_CACHE_DIR", str(tmp_path / "mesh-cache"))
    cases = list(_cases(tmp_path))
    assert len(cases) >= 500
    assert {c.kind for c in cases} == {"urdf", "xacro", "mjcf", "yaml"}
    outcomes: dict[int, str] = {}
    failures: list[str] = []

    def run(case: Case) -> None:
        try:
            outcomes[case.index] = _load(case)
        except Exception as exc:  # the point of the test: nothing outside the hierarchy
            failures.append(f"case {case.index} ({case.kind}, {case.mutation}, {case.path.name}): "
                            f"{type(exc).__name__}: {str(exc)[:300]}")

    # xacro cases wait on their worker process: run them side by side; the rest in this thread
    xacro_cases = [c for c in cases if c.kind in ("xacro", "yaml")]
    with ThreadPoolExecutor(max_workers=3, thread_name_prefix="fuzz") as pool:
        list(pool.map(run, xacro_cases))
    for case in cases:
        if case.kind not in ("xacro", "yaml"):
            run(case)
    assert not failures, "\n".join(failures)
    loaded = [c for c in cases if outcomes[c.index] == "loaded"]
    refused = len(cases) - len(loaded)
    assert loaded and refused, f"{len(loaded)} loaded, {refused} refused: the mutations test nothing"

    # a sample of what loaded goes through MuJoCo's compile and a few ticks, in worker processes
    sample = random.Random(SEED).sample(loaded, min(len(loaded), 16))
    with ProbePool(workers=2, timeout=120) as pool:
        results = pool.run([{"robot": str(c.path), "backend": "mujoco", "duration": 0.02} for c in sample])
    for case, r in zip(sample, results, strict=True):
        assert not r.get("died"), f"case {case.index} ({case.mutation}) killed MuJoCo's worker: {r.get('error')}"
        assert not r.get("unexpected"), f"case {case.index} ({case.mutation}): {r['error_type']}: {r['error']}"
