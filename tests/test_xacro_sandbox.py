"""Robot files are data (issue 20 item 3, acceptance 3): xacro escapes refused, limits, package roots."""

from __future__ import annotations

import html
import os
import sys
import time
from pathlib import Path

import pytest

from agentsdk.description import load_description, xacro_expand
from agentsdk.description.packages import Resolver
from agentsdk.description.xacro_expand import run_xacro
from agentsdk.description.xacro_sandbox import ExpressionRefused, check_expression
from agentsdk.errors import DescriptionError

HEAD = '<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro">\n'
LINK = '  <link name="base"/>\n'


def _package(root: Path) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "package.xml").write_text("<package><name>pkg</name></package>")
    return root


def _xacro(path: Path, body: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(HEAD + body + "</robot>\n")
    return path


@pytest.fixture
def canary(tmp_path: Path) -> Path:
    return tmp_path / "CANARY"


# every payload tries to create the canary file (or run a command that would); {c} is its path
ESCAPES = [
    "__import__('os').system('touch {c}')",
    "__builtins__",
    "().__class__.__bases__[0].__subclasses__()",
    "[c for c in ().__class__.__base__.__subclasses__() if c.__name__ == 'catch_warnings'][0]()"
    "._module.__builtins__['open']('{c}', 'w')",
    "python.type.__subclasses__(python.type)",
    "python.type(0).mro()[1].__subclasses__()",
    "python.vars(python.type)['__subclasses__'](python.type)",
    "python.list(python.map(python.vars, [python.type]))",
    "python.sorted([python.type, python.type], key=python.vars)",
    "python.list(python.filter(python.vars, [python.type]))",
    "python.vars",
    "xacro.dotify(python.vars(python))",
    "open('{c}', 'w')",
    "eval(\"open('{c}', 'w')\")",
    "exec(\"open('{c}', 'w')\")",
    "getattr(python, 'type')",
    "(lambda: open('{c}', 'w'))()",
    "(g for g in [1]).gi_frame.f_back.f_globals",
    "[g for g in [python.len]][0].__self__.open('{c}', 'w')",
    "python.len.__self__.open('{c}', 'w')",
    "(x := 1)",
    "f\"{{python.type}}\"",
    "'{{0.__class__}}'.format(1)",
    "'{{0}}'.format(python.type)",
    "xacro.load_yaml.__globals__['os'].system('touch {c}')",
    "xacro.arg.__code__",
    "math.parent.root",
    "9**9**8",
    "'a' * 10**10",
    "[0] * 10**10",
    "1 << 10**10",
    "10**10**10",
]


@pytest.mark.parametrize("payload", ESCAPES)
def test_xacro_escape_payloads_run_nothing(tmp_path: Path, canary: Path, payload: str) -> None:
    text = html.escape(payload.format(c=canary), quote=True)  # as it would stand in an attribute
    path = _xacro(_package(tmp_path / "pkg") / "evil.urdf.xacro", f'  <link name="x${{{text}}}"/>\n')
    with pytest.raises(DescriptionError) as info:
        load_description(path)
    assert not canary.exists()
    message = str(info.value)
    assert str(path) in message
    assert "\n" not in message
    # refused by the sandbox, or a name xacro does not define (open, eval, exec, getattr)
    assert "refused" in message or "is not defined" in message, message


@pytest.mark.parametrize(
    "payload",
    ["python.type(1)", "().__class__", "python.vars(python)", "(lambda: 0)()", "python.len.__self__"],
)
def test_a_refusal_names_file_line_and_construct(tmp_path: Path, payload: str) -> None:
    path = _xacro(_package(tmp_path / "pkg") / "evil.urdf.xacro", LINK + f'  <link name="x${{{payload}}}"/>\n')
    with pytest.raises(DescriptionError, match=r"evil\.urdf\.xacro:3: xacro expression .* refused: it ") as info:
        load_description(path)
    assert payload in str(info.value) and "trusted=True" in str(info.value)


def test_9_to_the_9_to_the_8_fails_within_5_seconds(tmp_path: Path) -> None:
    path = _xacro(_package(tmp_path / "pkg") / "pow.urdf.xacro", '  <xacro:property name="a" value="${9**9**8}"/>\n'
                  '  <link name="l${a}"/>\n')
    start = time.monotonic()
    with pytest.raises(DescriptionError, match=r"9\*\*43046721, an integer of more than"):
        load_description(path)
    assert time.monotonic() - start < 5.0


def test_substitution_eval_and_args_are_checked_too(tmp_path: Path, canary: Path) -> None:
    pkg = _package(tmp_path / "pkg")
    # a property's text becomes the $(eval ...) expression: xacro's "no '__'" rule alone lets this through
    path = _xacro(pkg / "e.urdf.xacro", f"""  <xacro:property name="p" value="open('{canary}', 'w')"/>
  <link name="$(eval ${{p}})"/>
""")
    with pytest.raises(DescriptionError):
        load_description(path)
    path = _xacro(pkg / "e2.urdf.xacro", '  <xacro:property name="p" value="().__class__"/>\n'
                  '  <link name="$(eval ${p})"/>\n')
    with pytest.raises(DescriptionError, match=r"\$\(eval \(\)\.__class__\) refused"):
        load_description(path)
    # an arg's value becomes a ${} expression
    path = _xacro(pkg / "a.urdf.xacro", '  <xacro:arg name="code" default="1"/>\n  <link name="l${$(arg code)}"/>\n')
    with pytest.raises(DescriptionError, match="refused"):
        load_description(path, {"code": f"python.len.__self__.open('{canary}', 'w')"})
    assert not canary.exists()
    assert load_description(path, {"code": "2*3"}).links == ("l6",)


def test_include_and_load_yaml_stay_inside_the_package(tmp_path: Path) -> None:
    pkg = _package(tmp_path / "pkg")
    (tmp_path / "outside.xacro").write_text(HEAD + '<link name="stolen"/></robot>\n')
    (tmp_path / "secret.yaml").write_text("key: stolen\n")
    (pkg / "link.xacro").symlink_to(tmp_path / "outside.xacro")
    cases = {
        '<xacro:include filename="/etc/passwd"/>': "xacro:include of '/etc/passwd' refused",
        '<xacro:include filename="../outside.xacro"/>': r"outside\.xacro' refused: .* outside the package roots",
        f'<xacro:include filename="{tmp_path / "outside.xacro"}"/>': "refused",
        '<xacro:include filename="link.xacro"/>': "refused",  # a symlink out of the package
        "<link name=\"${xacro.load_yaml('../secret.yaml')['key']}\"/>": "load_yaml of '../secret.yaml' refused",
        "<link name=\"${load_yaml('/etc/passwd')}\"/>": "load_yaml of '/etc/passwd' refused",
    }
    for body, pattern in cases.items():
        path = _xacro(pkg / "inc.urdf.xacro", LINK + "  " + body + "\n")
        with pytest.raises(DescriptionError, match=pattern) as info:
            load_description(path)
        assert "inc.urdf.xacro:3" in str(info.value), body
        # a file you trust may do it
        if "passwd" not in body:
            assert "stolen" in run_xacro(path, {}, Resolver(pkg, None, trusted=True), trusted=True)


def test_meshes_stay_inside_the_package(tmp_path: Path) -> None:
    pkg = _package(tmp_path / "pkg")
    (tmp_path / "outside.stl").write_bytes(b"solid x\nendsolid x\n")
    (pkg / "meshes").mkdir()
    (pkg / "meshes" / "link.stl").symlink_to(tmp_path / "outside.stl")
    for filename in ("../outside.stl", str(tmp_path / "outside.stl"), (tmp_path / "outside.stl").as_uri(),
                     "meshes/link.stl", "meshes/../../outside.stl"):
        path = pkg / "r.urdf"
        path.write_text(f'<robot name="r"><link name="a"><visual><geometry><mesh filename="{filename}"/>'
                        "</geometry></visual></link></robot>")
        with pytest.raises(DescriptionError, match=r"r\.urdf, line 1: link 'a' <visual>: mesh .* refused: .*outside"):
            load_description(path)
        assert load_description(path, trusted=True).mesh_files == ((tmp_path / "outside.stl").resolve(),)


def test_expansion_has_time_and_memory_limits(tmp_path: Path) -> None:
    pkg = _package(tmp_path / "pkg")
    slow = _xacro(pkg / "slow.urdf.xacro", '  <link name="l${python.sum(python.range(10**12))}"/>\n')
    with pytest.raises(DescriptionError, match=r"took longer than 1 s|more than 1 s of CPU"):
        run_xacro(slow, {}, Resolver(pkg, None), seconds=1.0)
    big = _xacro(pkg / "big.urdf.xacro", '  <link name="l${python.len(python.list(python.range(10**9)))}"/>\n')
    with pytest.raises(DescriptionError, match="memory limit"):
        run_xacro(big, {}, Resolver(pkg, None), memory=256 << 20)


def test_the_time_limit_counts_from_the_workers_start_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Starting the worker (interpreter, imports) is the machine's cost: seconds in a loaded VM.

    A start-up slowed by 1.5 s (a sitecustomize that sleeps) does not use up a 1 s expansion
    limit; the expansion itself still gets 1 s and no more.
    """
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text("import time\ntime.sleep(1.5)\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(site), *sys.path]))
    pkg = _package(tmp_path / "pkg")
    path = _xacro(pkg / "ok.urdf.xacro", LINK)
    assert 'name="base"' in run_xacro(path, {}, Resolver(pkg, None), seconds=1.0)
    slow = _xacro(pkg / "slow.urdf.xacro", '  <link name="l${python.sum(python.range(10**12))}"/>\n')
    start = time.monotonic()
    with pytest.raises(DescriptionError, match=r"took longer than 1 s|more than 1 s of CPU"):
        run_xacro(slow, {}, Resolver(pkg, None), seconds=1.0)
    assert time.monotonic() - start < 30.0  # (stopped by the worker's own limit, not the parent's backstop)


def test_the_expansion_cache_follows_the_variables_the_file_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another variable (pytest's PYTEST_CURRENT_TEST changes every test) keeps the cached expansion;
    a variable the file reads through $(optenv) expands it again."""
    pkg = _package(tmp_path / "pkg")
    path = _xacro(pkg / "env.urdf.xacro", '  <link name="l_$(optenv AGENTSDK_TEST_LINK none)"/>\n')
    monkeypatch.delenv("AGENTSDK_TEST_LINK", raising=False)
    assert 'name="l_none"' in run_xacro(path, {}, Resolver(pkg, None))
    workers: list[Path] = []
    real = xacro_expand._worker_result

    def counted(p: Path, job: object, seconds: float) -> dict[str, object]:
        workers.append(p)
        return real(p, job, seconds)  # type: ignore[arg-type]

    monkeypatch.setattr(xacro_expand, "_worker_result", counted)
    monkeypatch.setenv("AGENTSDK_TEST_UNRELATED", "1")
    assert 'name="l_none"' in run_xacro(path, {}, Resolver(pkg, None))
    assert workers == []
    monkeypatch.setenv("AGENTSDK_TEST_LINK", "x")
    assert 'name="l_x"' in run_xacro(path, {}, Resolver(pkg, None))
    assert workers == [path]


def test_what_xacro_documents_still_works(tmp_path: Path) -> None:
    pkg = _package(tmp_path / "pkg")
    (pkg / "config").mkdir()
    (pkg / "config" / "arm.yaml").write_text("arm: {length: 0.5, names: [a, b]}\nangle: !degrees 180\n")
    path = _xacro(pkg / "ok.urdf.xacro", """  <xacro:property name="cfg" value="${xacro.load_yaml('config/arm.yaml')}"/>
  <xacro:property name="n" value="${python.len(cfg.arm.names)}"/>
  <link name="base"/>
  <link name="l_${n}_${'-'.join([s.upper() for s in cfg['arm']['names']])}_${int(round(cfg.angle / pi * 180))}"/>
  <link name="m_${max(2, min(3, 7)) if radians(180) == pi else 0}_${python.sorted([3, 1], key=python.abs)[0]}"/>
  <link name="e_$(eval 1 + 2)_${'%d' % (2**10)}_${math.floor(math.sqrt(16))}_${[i * i for i in range(3)][2]}"/>
  <joint name="j" type="revolute"><parent link="base"/><child link="l_2_A-B_180"/>
    <limit lower="${-cfg.arm.length}" upper="${cfg.arm.length}" effort="${2 ** 3}" velocity="1"/></joint>
  <joint name="f1" type="fixed"><parent link="base"/><child link="m_3_1"/></joint>
  <joint name="f2" type="fixed"><parent link="base"/><child link="e_3_1024_4_4"/></joint>
""")
    desc = load_description(path)
    assert desc.links == ("base", "l_2_A-B_180", "m_3_1", "e_3_1024_4_4")
    assert (desc.joint("j").lower, desc.joint("j").upper, desc.joint("j").max_effort) == (-0.5, 0.5, 8.0)


def test_trusted_runs_xacro_unchecked(tmp_path: Path) -> None:
    path = _xacro(_package(tmp_path / "pkg") / "t.urdf.xacro", '  <link name="l${python.len(python.vars(math))}"/>\n')
    with pytest.raises(DescriptionError, match="refused"):
        load_description(path)
    assert load_description(path, trusted=True).links == ("l5",)


def test_expansion_changes_nothing_in_this_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """xacro runs in its worker: no ament_index_python swap, no xacro state in the caller's process."""
    monkeypatch.setenv("AGENTSDK_PACKAGE_PATH", str(tmp_path))
    _package(tmp_path / "pkg")
    path = _xacro(tmp_path / "pkg" / "f.urdf.xacro", '  <link name="x$(find pkg)"/>\n')
    before = {k for k in sys.modules if k.startswith(("ament_index_python", "xacro"))}
    desc = load_description(path)
    assert desc.links == (f"x{(tmp_path / 'pkg').resolve()}",)
    assert {k for k in sys.modules if k.startswith(("ament_index_python", "xacro"))} == before


@pytest.mark.parametrize(
    ("expr", "construct"),
    [
        ("a.__class__", "attribute '__class__'"),
        ("a._private", "attribute '_private'"),
        ("__x", "name '__x'"),
        ("lambda: 1", "a lambda"),
        ("f'{a}'", "an f-string"),
        ("(y := 2)", ":="),
        ("[0 for a.b in c]", "assigns the attribute"),
    ],
)
def test_static_check_names_the_construct(expr: str, construct: str) -> None:
    with pytest.raises(ExpressionRefused, match=construct.replace("(", r"\(").replace(")", r"\)")):
        check_expression(expr)


def test_a_worker_that_cannot_start_is_a_description_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _xacro(_package(tmp_path / "pkg") / "w.urdf.xacro", LINK)
    monkeypatch.setattr(sys, "executable", os.fspath(tmp_path / "no-python"))
    with pytest.raises(DescriptionError, match="cannot start the xacro worker"):
        load_description(path)


def test_mjcf_includes_and_assets_stay_inside_the_package(tmp_path: Path) -> None:
    import shutil

    pkg = _package(tmp_path / "pkg")
    shutil.copytree(Path(__file__).parent / "fixtures" / "mjcf_arm", pkg / "arm")
    assert load_description(pkg / "arm" / "scene.xml").joint_names  # inside: loads
    (tmp_path / "outside.xml").write_text("<mujoco/>")
    scene = (pkg / "arm" / "scene.xml").read_text()
    for target in ("/etc/passwd", "../../outside.xml", str(tmp_path / "outside.xml")):
        (pkg / "arm" / "evil.xml").write_text(scene.replace('<include file="arm.xml"/>',
                                                            f'<include file="arm.xml"/><include file="{target}"/>'))
        with pytest.raises(DescriptionError, match=r"evil\.xml, line \d+: <include file=.* refused: .*outside"):
            load_description(pkg / "arm" / "evil.xml")
    arm = (pkg / "arm" / "arm.xml").read_text()
    (pkg / "arm" / "arm2.xml").write_text(arm.replace('meshdir="assets"', f'meshdir="{tmp_path}"'))
    with pytest.raises(DescriptionError, match=r"<mesh file=.* refused"):
        load_description(pkg / "arm" / "arm2.xml")
