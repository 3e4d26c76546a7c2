"""``agentsdk bench``: run every benchmark, each figure next to its raw baseline from the same run.

    agentsdk bench                     # everything (a few minutes); also `python -m agentsdk.bench`
    agentsdk bench --quick             # shorter runs, same structure
    agentsdk bench --only overhead     # one benchmark (repeatable, or comma-separated)
    agentsdk bench --only anchors      # gymnasium and dm_control beside agentsdk (not in a plain --quick)
    agentsdk bench --only instructions # the awaited cycle in instructions (valgrind; not in a plain --quick)
    agentsdk bench --json out.json     # also write the full results (raw data, tables) as JSON
    agentsdk bench --verbose           # every benchmark's table as it finishes
    agentsdk bench --list              # the benchmark names

A summary of every comparison goes to stdout (``--verbose``: also each benchmark's full
table as it finishes); progress goes to stderr; JSON only when asked (``--json PATH``,
``--json -`` for stdout).

Benchmarks written in other modules (``bench/feedback_timing.py``,
``bench/safety_latency.py``, ``bench/can_cycle.py``) are called if present: the
first of ``run``, ``bench``, ``benchmark``, ``run_benchmark``, ``run_bench``,
``measure``, ``main`` they define, with ``quick=`` if it takes it. They may return a
:class:`agentsdk.bench.common.Section` (or a list of them, or a list of ``Comparison``), a
JSON-able dict, or print their own table and JSON (parsed from their output).
CAN needs a SocketCAN ``vcan0``: without one here, ``can_cycle`` runs inside the
user-mode-linux VM of ``scripts/run-in-vcan.sh`` and its results come back as JSON.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import importlib
import inspect
import io
import json
import os
import subprocess
import sys
import tempfile
import time
import traceback
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from agentsdk.bench.common import (
    COMPARISON_HEADERS,
    Comparison,
    Section,
    format_table,
    machine_info,
    machine_line,
    progress,
    to_jsonable,
    write_json,
)

BENCH_DIR = Path(__file__).resolve().parent
INNER_ENV = "AGENTSDK_BENCH_INNER"
ENTRY_POINTS = ("run", "bench", "benchmark", "run_benchmark", "run_bench", "measure", "main")

Runner = Callable[[bool], list[Section]]


# --------------------------------------------------------------------------- own benchmarks


def _overhead(quick: bool) -> list[Section]:
    from agentsdk.bench import overhead

    return [overhead.run_overhead(quick)]


def _rtf(quick: bool) -> list[Section]:
    from agentsdk.bench import overhead

    return [overhead.run_rtf(quick)]


def _sensors(quick: bool) -> list[Section]:
    from agentsdk.bench import sensors

    return [sensors.run(quick)]


def _realtime(quick: bool) -> list[Section]:
    from agentsdk.bench import realtime

    return [realtime.run(quick)]


def _multi(quick: bool) -> list[Section]:
    from agentsdk.bench import multi

    return [multi.run(quick)]


def _ros2_serve(quick: bool) -> list[Section]:
    from agentsdk.bench import ros2_serve

    return [ros2_serve.run(quick)]


def _recording(quick: bool) -> list[Section]:
    from agentsdk.bench import recording

    return [recording.run(quick)]


def _planning(quick: bool) -> list[Section]:
    from agentsdk.bench import planning

    return [planning.run(quick)]


def _anchors(quick: bool, setup: bool = False) -> list[Section]:
    from agentsdk.bench import anchors

    return [anchors.run(quick, setup=setup)]


def _tracking(quick: bool) -> list[Section]:
    from agentsdk.bench import tracking

    return [tracking.run(quick)]


def _instructions(quick: bool, setup: bool = False) -> list[Section]:
    from agentsdk.bench import instructions

    return [instructions.run(quick, setup=setup)]


def _block(quick: bool) -> list[Section]:
    return run_external("block", "block lockstep: hold and track, block vs tick-by-tick vs the raw loop", quick)


# --------------------------------------------------------------------------- other modules


class _Tee(io.TextIOBase):
    """Writes through to the real stdout and keeps a copy (to parse JSON a module printed)."""

    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.buf = io.StringIO()

    def write(self, s: str) -> int:
        self.out.write(s)
        self.buf.write(s)
        return len(s)

    def flush(self) -> None:
        self.out.flush()


def _json_blocks(text: str) -> list[Any]:
    """Top-level JSON objects/arrays found in printed text (each starting a line)."""
    dec = json.JSONDecoder()
    out: list[Any] = []
    pos = 0
    while pos < len(text):
        starts = [i for i in (text.find("\n{", pos), text.find("\n[", pos)) if i >= 0]
        if pos == 0 and text[:1] in "{[":
            k = 0
        elif starts:
            k = min(starts) + 1
        else:
            break
        try:
            obj, end = dec.raw_decode(text, k)
        except json.JSONDecodeError:
            pos = k + 1
            continue
        if isinstance(obj, dict | list) and obj:
            out.append(obj)
        pos = end
    return out


def _argv_param(fn: Callable[..., Any]) -> str | None:
    """The parameter that takes a command line (``argv``, or ``args`` annotated as a list of str), if any."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return None
    if "argv" in params:
        return "argv"
    p = params.get("args")
    if p is not None and p.kind is not p.VAR_POSITIONAL:
        ann = str(p.annotation)
        if "Namespace" not in ann and ("list" in ann or "Sequence" in ann):
            return "args"
    return None


def _unsupplied(fn: Callable[..., Any]) -> list[str]:
    """Required parameters of ``fn`` this runner cannot supply (it supplies ``quick`` and a command line)."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return []
    argv = _argv_param(fn)
    return [
        p.name
        for p in params.values()
        if p.default is inspect.Parameter.empty
        and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
        and p.name not in ("quick", argv)
    ]


def _find_entry(mod: Any) -> tuple[tuple[str, Callable[..., Any]] | None, list[str]]:
    """The first entry point callable without extra arguments, and the ones skipped (with why)."""
    skipped: list[str] = []
    for name in ENTRY_POINTS:
        fn = getattr(mod, name, None)
        if not callable(fn) or getattr(fn, "__module__", mod.__name__) != mod.__name__:
            continue
        missing = _unsupplied(fn)
        if missing:
            skipped.append(f"{name}({', '.join(missing)})")
            continue
        return (name, fn), skipped
    return None, skipped


#: shorter runs for --quick, for modules whose command line has no --quick (tried first; dropped if rejected)
QUICK_ARGV: dict[str, list[str]] = {
    "feedback_timing": ["--duration", "1"],
    "safety_latency": ["--trials", "10", "--stall-trials", "5"],
}


def _call(fn: Callable[..., Any], name: str, module: Any, quick: bool) -> Any:
    """Call an entry point defensively.

    ``quick=`` if it takes it; else, in quick mode, a shorter command line (``--quick`` if the
    module mentions it, or :data:`QUICK_ARGV`), retried with no arguments if its parser rejects
    it. The command line goes to its ``argv`` parameter, and ``sys.argv`` is set to it meanwhile.
    """
    params = inspect.signature(fn).parameters
    short = module.__name__.rsplit(".", 1)[-1]
    prog = f"bench/{short}.py"
    kwargs: dict[str, Any] = {}
    if "quick" in params:
        kwargs["quick"] = quick
    argv_param = _argv_param(fn)
    attempts: list[list[str]] = [[]]
    if quick and "quick" not in params:
        try:
            source = inspect.getsource(module)
        except (OSError, TypeError):
            source = ""
        quick_argv = ["--quick"] if "--quick" in source else QUICK_ARGV.get(short, [])
        if quick_argv:
            attempts.insert(0, quick_argv)
    missing = [m for m in _unsupplied(fn) if m not in kwargs]
    if missing:
        raise TypeError(f"{name}() needs arguments this runner cannot supply: {', '.join(missing)}")

    saved = sys.argv
    try:
        for k, argv in enumerate(attempts):
            sys.argv = [prog, *argv]
            if argv_param is not None:
                kwargs[argv_param] = list(argv)
            try:
                res = fn(**kwargs)
                if inspect.isawaitable(res):
                    res = asyncio.run(_await(res))
                return res
            except SystemExit as exc:
                if exc.code in (0, None):
                    return None
                if k == len(attempts) - 1:
                    raise RuntimeError(f"{name}({' '.join(argv)}) exited with status {exc.code}") from None
                progress(f"{short}: its command line rejected {' '.join(argv)!r}; running it with defaults")
    finally:
        sys.argv = saved
    return None


async def _await(aw: Any) -> Any:
    return await aw


def _adapt_feedback_timing(doc: Any) -> list[Comparison]:
    """bench/feedback_timing.py's JSON (rows of LoopStats per rate and loop) -> run_feedback vs bare asyncio."""
    rows = doc["results"] if isinstance(doc, dict) else doc
    by = {(float(r["rate"]), r["loop"]): r for r in rows}
    out: list[Comparison] = []
    for rate in sorted({float(r["rate"]) for r in rows}):
        base, sdk = by.get((rate, "asyncio.sleep(deadline)")), by.get((rate, "run_feedback"))
        if base is None or sdk is None:
            continue
        lbl = "raw asyncio"
        hz = f"{rate:g} Hz"
        out += [
            Comparison(
                f"{hz}: period error p99",
                "µs",
                base["period_error_p99"] * 1e6,
                sdk["period_error_p99"] * 1e6,
                baseline_label=lbl,
            ),
            Comparison(
                f"{hz}: period error max",
                "µs",
                base["period_error_max"] * 1e6,
                sdk["period_error_max"] * 1e6,
                baseline_label=lbl,
            ),
            Comparison(
                f"{hz}: wake latency p99", "µs", base["latency_p99"] * 1e6, sdk["latency_p99"] * 1e6, baseline_label=lbl
            ),
            Comparison(
                f"{hz}: achieved rate",
                "Hz",
                base["achieved_rate"],
                sdk["achieved_rate"],
                baseline_label=lbl,
                lower_is_better=False,
            ),
            Comparison(
                f"{hz}: missed deadlines",
                "periods",
                float(base["missed_deadlines"]),
                float(sdk["missed_deadlines"]),
                baseline_label=lbl,
            ),
        ]
    return out


def _adapt_safety_latency(doc: Any) -> list[Comparison]:
    """bench/safety_latency.py's JSON -> p99 latencies (no raw counterpart: baseline column empty)."""
    out: list[Comparison] = []
    for backend, res in doc.get("estop", {}).items():
        for measure, st in res.items():
            out.append(
                Comparison(
                    f"e-stop {backend} {measure}: latency p99", "ms", None, st["p99_ms"], baseline_label="", extra=st
                )
            )
    for kind, per in doc.get("stall", {}).items():
        for timeout, st in per.items():
            out.append(
                Comparison(
                    f"stall ({kind}), stall_timeout {timeout} s: detection after timeout, p99",
                    "ms",
                    None,
                    st["p99_ms"],
                    baseline_label="",
                    extra=st,
                )
            )
    return out


#: turn a module's own JSON into comparisons (best effort: on any mismatch its JSON is kept as is)
ADAPTERS: dict[str, Callable[[Any], list[Comparison]]] = {
    "feedback_timing": _adapt_feedback_timing,
    "safety_latency": _adapt_safety_latency,
}


def _to_sections(name: str, title: str, result: Any, printed: str) -> list[Section]:
    if isinstance(result, Section):
        return [result]
    if isinstance(result, list | tuple) and result and all(isinstance(r, Section) for r in result):
        return list(result)
    sec = Section(name, title)
    if isinstance(result, list | tuple) and result and all(isinstance(r, Comparison) for r in result):
        sec.comparisons = list(result)
        return [sec]
    if isinstance(result, dict) and isinstance(result.get("comparisons"), list):
        try:
            return [Section.from_json({"name": name, "title": title, **result})]
        except (KeyError, TypeError):
            pass
    doc: Any = None
    if result is not None and not isinstance(result, bool | int) and result != {} and result != []:
        doc = to_jsonable(result)
        sec.data = {"result": doc}
        origin = "its returned result"
    else:
        blocks = _json_blocks(printed)
        if blocks:
            doc = blocks[-1]
            sec.data = {"printed_json": doc if len(blocks) == 1 else blocks}
            origin = "its printed JSON"
    if doc is None:
        sec.notes.append("no result returned and no JSON printed: see its printed output above")
        return [sec]
    adapter = ADAPTERS.get(name)
    if adapter is not None:
        try:
            sec.comparisons = adapter(doc)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            sec.notes.append(f"could not read figures from {origin} ({exc!r}); it is kept in the JSON output")
    if sec.comparisons:
        sec.notes.append(f"figures read from {origin} by bench/__main__.py; its own table is printed above")
    elif adapter is None:
        sec.notes.append(f"{origin} is kept in the JSON output; its own table is printed above")
    return [sec]


def run_external(name: str, title: str, quick: bool) -> list[Section]:
    path = BENCH_DIR / f"{name}.py"
    if not path.is_file():
        return [Section(name, title, status="missing", notes=[f"bench/{name}.py does not exist: nothing measured"])]
    mod = importlib.import_module(f"agentsdk.bench.{name}")
    entry, skipped = _find_entry(mod)
    if entry is None:
        why = f" (found only {', '.join(skipped)}, which need arguments)" if skipped else ""
        return [
            Section(
                name,
                title,
                status="missing",
                notes=[
                    f"bench/{name}.py defines none of {', '.join(f'{e}()' for e in ENTRY_POINTS)} "
                    f"callable without arguments{why}: not run"
                ],
            )
        ]
    fname, fn = entry
    progress(f"{name}: calling bench.{name}.{fname}(){' (quick)' if quick else ''}")
    tee = _Tee(sys.stdout)
    with contextlib.redirect_stdout(tee):
        result = _call(fn, fname, mod, quick)
    sys.stdout.flush()
    secs = _to_sections(name, title, result, tee.buf.getvalue())
    for s in secs:
        s.data.setdefault("entry_point", f"agentsdk.bench.{name}.{fname}")
    return secs


def _feedback_timing(quick: bool) -> list[Section]:
    return run_external("feedback_timing", "realtime loop timing at 500 Hz and 1 kHz vs a raw asyncio loop", quick)


def _safety_latency(quick: bool) -> list[Section]:
    return run_external("safety_latency", "e-stop and stall-watchdog latency", quick)


def _can_cycle(quick: bool) -> list[Section]:
    title = "CAN cycle rates on vcan0 vs raw python-can and the wire limit"
    if not (BENCH_DIR / "can_cycle.py").is_file():
        return [
            Section("can_cycle", title, status="missing", notes=["bench/can_cycle.py does not exist: nothing measured"])
        ]
    if Path("/sys/class/net/vcan0").exists() or os.environ.get(INNER_ENV):
        secs = run_external("can_cycle", title, quick)
        if not os.environ.get(INNER_ENV):
            for s in secs:
                s.notes.append("measured on this machine's own vcan0 interface")
        return secs
    # no vcan0 here: run the benchmark inside the user-mode-linux kernel of scripts/run-in-vcan.sh
    import agentsdk

    script = Path(agentsdk.__file__).resolve().parent / "data" / "run-in-vcan.sh"
    if not script.is_file():
        return [Section("can_cycle", title, status="skipped", notes=[f"no vcan0 and no {script}"])]
    fd, tmp = tempfile.mkstemp(suffix=".json", prefix="bench-can-", dir=tempfile.gettempdir())
    os.close(fd)
    cmd = ["bash", str(script), sys.executable, "-m", "agentsdk.bench", "--inner", "--only", "can_cycle", "--json", tmp]
    if quick:
        cmd.append("--quick")
    env = {**os.environ, INNER_ENV: "1", "VCAN_TIMEOUT": os.environ.get("VCAN_TIMEOUT", "900")}
    progress("can_cycle: no vcan0 here; running it inside the user-mode-linux VM (scripts/run-in-vcan.sh)")
    sys.stdout.flush()
    t0 = time.perf_counter()
    # the VM's stdout goes straight to ours; its stderr is streamed to ours and its tail kept for errors
    err_tail: deque[str] = deque(maxlen=15)
    with subprocess.Popen(cmd, env=env, stdout=sys.stdout, stderr=subprocess.PIPE, text=True) as proc:
        assert proc.stderr is not None
        for line in proc.stderr:
            sys.stderr.write(line)
            err_tail.append(line.rstrip("\n"))
            if time.perf_counter() - t0 > 1000:
                proc.kill()
                err_tail.append("(killed after 1000 s)")
                break
        returncode = proc.wait()
    wall = time.perf_counter() - t0
    tail = "\n".join(err_tail)
    try:
        data = json.loads(Path(tmp).read_text(encoding="utf-8") or "{}")
    except (OSError, json.JSONDecodeError):
        data = {}
    finally:
        Path(tmp).unlink(missing_ok=True)
    secs = [Section.from_json(s) for s in data.get("sections", [])]
    if not secs:
        return [
            Section(
                "can_cycle",
                title,
                status="error",
                notes=[f"the vcan VM run exited {returncode} without results; its stderr ended with:\n{tail}"],
            )
        ]
    vm = data.get("machine", {})
    for s in secs:
        s.notes.append(
            "measured inside a user-mode-linux VM with a real SocketCAN vcan0 (scripts/run-in-vcan.sh): one vCPU, "
            "slow syscalls, so absolute rates are lower than on a host kernel; the raw python-can baseline ran in "
            f"the same VM ({wall:.0f} s incl. boot; VM cpu: {vm.get('cpu', '?')}, {vm.get('cores', '?')} core(s))"
        )
        s.data["ran_in"] = "user-mode-linux vcan0 (scripts/run-in-vcan.sh)"
        s.data["vm_machine"] = vm
    return secs


# --------------------------------------------------------------------------- driver

BENCHMARKS: dict[str, tuple[str, Runner]] = {
    "overhead": ("SDK overhead per control cycle vs raw MuJoCo / PyBullet loops", _overhead),
    "rtf": ("lockstep real-time factor vs the raw simulators", _rtf),
    "anchors": ("env step ÷ raw mj_step: agentsdk beside gymnasium and dm_control", _anchors),
    "multi": ("many lockstep robots in one event loop vs one robot", _multi),
    "realtime": ("realtime control-loop pacing at 500 Hz / 1 kHz vs raw pacing loops", _realtime),
    "feedback_timing": ("realtime loop timing at 500 Hz / 1 kHz vs a raw asyncio loop", _feedback_timing),
    "can_cycle": ("CAN cycle rates on vcan0 vs raw python-can and the wire limit", _can_cycle),
    "safety_latency": ("e-stop and stall latency", _safety_latency),
    "planning": ("trajectory planning time vs raw ruckig", _planning),
    "tracking": ("hand off a 10 cm line: inverse-dynamics feed-forward vs g(q) only", _tracking),
    "ros2_serve": ("serving joint_states on ROS 2: lockstep cost and tick -> peer latency vs raw DDS", _ros2_serve),
    "recording": (
        "recording cost: arm3 lockstep recorded vs unrecorded, MB per robot-minute, read-back memory", _recording
    ),
    "sensors": ("MuJoCo camera sensor per frame vs mujoco.Renderer; sensors' cost per tick", _sensors),
    "block": ("block lockstep (the default) vs tick-by-tick (opted out) vs the raw loop: hold and track", _block),
    "instructions": ("one awaited command per tick, MuJoCo: instructions per cycle (cachegrind) vs the raw loop",
                     _instructions),
}
ALIASES = {
    "ros2": "ros2_serve",
    "feedback": "feedback_timing",
    "pacing": "realtime",
    "robots": "multi",
    "timing": "feedback_timing",
    "can": "can_cycle",
    "safety": "safety_latency",
    "latency": "safety_latency",
    "plan": "planning",
    "trajectory": "planning",
    "real_time_factor": "rtf",
    "record": "recording",
    "gymnasium": "anchors",
    "dm_control": "anchors",
}


#: left out of a plain ``--quick`` run (each runs when named with ``--only``, quick or not), and why
NOT_IN_QUICK = {
    "anchors": "third-party stacks (gymnasium; dm_control in an environment of its own): `--only anchors`",
    "instructions": "valgrind, a few minutes: `--only instructions`",
}
#: benchmarks that may set up what they need (a pinned environment, pip) only when named with ``--only``
SETS_UP_WHEN_NAMED = {"anchors": _anchors, "instructions": _instructions}


def _selected(only: list[str] | None) -> list[str]:
    if not only:
        return list(BENCHMARKS)
    names: list[str] = []
    for item in only:
        for raw in item.split(","):
            n = raw.strip().replace("-", "_")
            n = ALIASES.get(n, n)
            if n.endswith(".py"):
                n = n[:-3]
            if n not in BENCHMARKS:
                raise SystemExit(f"unknown benchmark {raw!r}; choose from: {', '.join(BENCHMARKS)}")
            if n not in names:
                names.append(n)
    return names


def _summary(sections: list[Section]) -> str:
    rows = []
    for s in sections:
        if not s.comparisons:
            why = {"missing": "MISSING", "error": "ERROR", "skipped": "SKIPPED"}.get(s.status, "see its table above")
            rows.append([s.name, why, "", "", "", "", "", ""])
        for c in s.comparisons:
            rows.append([s.name, *c.row()])
    return format_table(("section", *COMPARISON_HEADERS), rows)


def _loadavg() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def _round(x: Any, digits: int = 4) -> Any:
    if isinstance(x, float):
        return float(f"{x:.{digits}g}")
    if isinstance(x, dict):
        return {k: _round(v, digits) for k, v in x.items()}
    if isinstance(x, list):
        return [_round(v, digits) for v in x]
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="agentsdk bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter runs (same structure)")
    ap.add_argument("--json", metavar="PATH",
                    help="write the full results as JSON to PATH (`-`: to stdout, instead of the tables)")
    ap.add_argument("--verbose", "-v", action="store_true",
                    help="print every benchmark's full table as it finishes (default: the summary only)")
    ap.add_argument("--only", action="append", metavar="NAME", help="run only these benchmarks (repeatable, a,b)")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    ap.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)  # inside the vcan VM
    args = ap.parse_args(argv)
    if args.list:
        for name, (title, _) in BENCHMARKS.items():
            print(f"{name:16s} {title}")
        return 0
    names = _selected(args.only)

    info = machine_info()
    info["loadavg_1m_start"] = _loadavg()
    if not args.inner and args.json != "-":
        print(machine_line(info) + f"; load avg {info['loadavg_1m_start']} at start", flush=True)
        print(f"mode: {'quick' if args.quick else 'full'}; benchmarks: {', '.join(names)}", flush=True)
        load, cores = info["loadavg_1m_start"], info["usable_cores"] or 1
        if load is not None and load > 0.75 * cores:
            print(
                f"WARNING: the machine is busy (load average {load} on {cores} cores): wall-clock figures are "
                "inflated; trust the ratios and the CPU-time rows more than absolute wall times.",
                flush=True,
            )
        print(flush=True)

    sections: list[Section] = []
    t_all = time.perf_counter()
    for name in names:
        title, runner = BENCHMARKS[name]
        t0 = time.perf_counter()
        if args.quick and not args.only and name in NOT_IN_QUICK:
            sections.append(Section(name, title, status="skipped", notes=[f"not in --quick: {NOT_IN_QUICK[name]}"]))
            continue
        try:
            if name in SETS_UP_WHEN_NAMED and args.only:
                secs = SETS_UP_WHEN_NAMED[name](args.quick, True)
            else:
                secs = runner(args.quick)
        except Exception as exc:
            tb = traceback.format_exc(limit=-3)
            progress(f"{name} failed: {exc!r}")
            secs = [Section(name, title, status="error", notes=[f"{type(exc).__name__}: {exc}", tb.strip()])]
        dt = time.perf_counter() - t0
        for s in secs:
            if not s.seconds:
                s.seconds = dt / len(secs)
            if args.verbose and not args.inner:  # (inside the vcan VM the outer run prints them)
                print(s.render(), flush=True)
                print(flush=True)
        sections += secs
    total = time.perf_counter() - t_all
    info["loadavg_1m_end"] = _loadavg()

    full = {
        "machine": info,
        "machine_line": machine_line(info),
        "mode": "quick" if args.quick else "full",
        "total_seconds": round(total, 1),
        "sections": [s.to_json() for s in sections],
    }
    if args.json == "-":
        print(json.dumps(to_jsonable(full), indent=2, ensure_ascii=False))
        return 0
    if args.json:
        write_json(args.json, full)
    if args.inner:
        return 0

    print(f"== summary: every figure next to its baseline from this run ({total:.0f} s total)")
    print()
    print(_summary(sections))
    print()
    print(machine_line(info) + f"; load avg {info['loadavg_1m_start']} at start, {info['loadavg_1m_end']} at end")
    if args.json:
        print(f"\nfull results (raw data, tables, profiles) written to {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
