"""Shared helpers of the benchmarks: the machine line, timing statistics, side-by-side tables, JSON.

Every benchmark reports *figures* next to a *baseline measured in the same run*
(a raw simulator loop, a raw asyncio loop, raw python-can, raw ruckig, ...), so
the ratios hold across machines even where absolute times do not. A benchmark
module returns a :class:`Section`::

    from agentsdk.bench.common import Comparison, Section

    def run(quick: bool = False) -> Section:
        sec = Section("my_bench", "What it measures")
        sec.comparisons.append(Comparison("arm3 mujoco: time per cycle", "µs", baseline=27.1, sdk=171.4))
        return sec

``agentsdk bench`` prints each section as it finishes, then one summary table
of every comparison and the JSON of the whole run.
"""

from __future__ import annotations

import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

__all__ = [
    "Comparison",
    "Section",
    "Table",
    "fmt",
    "format_table",
    "machine_info",
    "machine_line",
    "median",
    "progress",
    "spread",
    "timed",
    "to_jsonable",
    "write_json",
]


# --------------------------------------------------------------------------- machine


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown cpu"


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def machine_info() -> dict[str, Any]:
    """CPU model, core counts, OS and the versions that matter for the figures."""
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count() or 0
    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count() or 0,
        "usable_cores": usable,
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "python_impl": platform.python_implementation(),
        "numpy": _version("numpy"),
        "mujoco": _version("mujoco"),
        "pybullet": _version("pybullet"),
        "ruckig": _version("ruckig"),
        "python_can": _version("python-can"),
        "agentsdk": _version("agentsdk"),
    }


def machine_line(info: dict[str, Any] | None = None) -> str:
    i = info if info is not None else machine_info()
    cores = f"{i['cores']} cores" + (f" ({i['usable_cores']} usable)" if i["usable_cores"] != i["cores"] else "")
    return (
        f"machine: {i['cpu']}, {cores}, {i['os']}; {i['python_impl']} {i['python']}, numpy {i['numpy']}, "
        f"mujoco {i['mujoco']}, pybullet {i['pybullet']}, ruckig {i['ruckig']}, python-can {i['python_can']}"
    )


# --------------------------------------------------------------------------- statistics


def median(values: Iterable[float]) -> float:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return statistics.median(vals) if vals else math.nan


def spread(values: Sequence[float]) -> dict[str, float]:
    """median/min/max of repeated measurements (for the JSON)."""
    vals = [float(v) for v in values]
    if not vals:
        return {"median": math.nan, "min": math.nan, "max": math.nan, "n": 0}
    return {"median": statistics.median(vals), "min": min(vals), "max": max(vals), "n": len(vals)}


def progress(msg: str) -> None:
    """Progress on stderr, so stdout holds only the tables and the JSON."""
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- formatting


def fmt(value: Any, digits: int = 3) -> str:
    """A number with about ``digits`` significant digits (no exponent for ordinary magnitudes)."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        a = abs(value)
        if a == 0.0:
            return "0"
        if a >= 10 ** (digits + 3) or a < 1e-4:
            return f"{value:.{max(digits - 1, 1)}e}"
        decimals = max(digits - 1 - math.floor(math.log10(a)), 0)
        return f"{value:.{decimals}f}"
    return str(value)


def _is_numeric(cell: str) -> bool:
    s = cell.strip().lstrip("+-~<>").rstrip("x%")
    try:
        float(s)
        return True
    except ValueError:
        return False


def format_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], title: str | None = None) -> str:
    """A plain-text table; numeric columns right-aligned."""
    cells = [[c if isinstance(c, str) else fmt(c) for c in row] for row in rows]
    cols = len(headers)
    widths = [len(h) for h in headers]
    for row in cells:
        for k, c in enumerate(row[:cols]):
            widths[k] = max(widths[k], len(c))
    numeric = [
        bool(cells) and all(_is_numeric(r[k]) or r[k] in ("-", "") for r in cells if k < len(r)) for k in range(cols)
    ]
    sep = "  "

    def line(row: Sequence[str]) -> str:
        out = []
        for k in range(cols):
            c = row[k] if k < len(row) else ""
            out.append(c.rjust(widths[k]) if numeric[k] else c.ljust(widths[k]))
        return sep.join(out).rstrip()

    rule = sep.join("-" * w for w in widths)
    parts = []
    if title:
        parts.append(title)
    parts += [line(list(headers)), rule, *(line(r) for r in cells)]
    return "\n".join(parts)


# --------------------------------------------------------------------------- results


@dataclass
class Comparison:
    """One figure next to its baseline from the same run.

    ``diff`` is ``sdk - baseline`` (the SDK's cost when lower is better) and
    ``ratio`` is ``sdk / baseline``. ``target`` is an optional bound on ``diff``
    (``diff_target``), on ``sdk`` (``sdk_target``) or on ``ratio`` (``ratio_target``),
    reported as met or not.
    """

    figure: str
    unit: str
    baseline: float | None
    sdk: float | None
    baseline_label: str = "raw"
    sdk_label: str = "agentsdk"
    lower_is_better: bool = True
    diff_target: float | None = None
    sdk_target: float | None = None
    note: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    ratio_target: float | None = None

    @property
    def diff(self) -> float | None:
        if self.baseline is None or self.sdk is None:
            return None
        return self.sdk - self.baseline

    @property
    def ratio(self) -> float | None:
        if self.baseline is None or self.sdk is None or self.baseline == 0:
            return None
        return self.sdk / self.baseline

    @property
    def target_met(self) -> bool | None:
        d = self.diff
        checks: list[bool] = []
        if self.diff_target is not None and d is not None:
            checks.append(d <= self.diff_target if self.lower_is_better else d >= self.diff_target)
        if self.sdk_target is not None and self.sdk is not None:
            checks.append(self.sdk <= self.sdk_target if self.lower_is_better else self.sdk >= self.sdk_target)
        r = self.ratio
        if self.ratio_target is not None and r is not None:
            checks.append(r <= self.ratio_target if self.lower_is_better else r >= self.ratio_target)
        return all(checks) if checks else None

    def target_text(self) -> str:
        met = self.target_met
        if met is None:
            return ""
        op = "<=" if self.lower_is_better else ">="
        bounds = []
        if self.diff_target is not None:
            bounds.append(f"diff {op} {fmt(self.diff_target)} {self.unit}")
        if self.sdk_target is not None:
            bounds.append(f"{op} {fmt(self.sdk_target)} {self.unit}")
        if self.ratio_target is not None:
            bounds.append(f"ratio {op} {fmt(self.ratio_target)}x")
        return f"{', '.join(bounds)}: {'MET' if met else 'NOT MET'}"

    def row(self) -> list[str]:
        r = self.ratio
        d = self.diff
        return [
            self.figure,
            self.unit,
            "-" if self.baseline is None else f"{fmt(self.baseline)} ({self.baseline_label})",
            fmt(self.sdk),
            "-" if d is None else (("+" if d > 0 else "") + fmt(d)),
            "-" if r is None else f"{fmt(r)}x",
            self.target_text(),
        ]

    def to_json(self) -> dict[str, Any]:
        return {
            "figure": self.figure,
            "unit": self.unit,
            "baseline": self.baseline,
            "baseline_label": self.baseline_label,
            "sdk": self.sdk,
            "sdk_label": self.sdk_label,
            "diff": self.diff,
            "ratio": self.ratio,
            "lower_is_better": self.lower_is_better,
            "diff_target": self.diff_target,
            "sdk_target": self.sdk_target,
            "ratio_target": self.ratio_target,
            "target_met": self.target_met,
            "note": self.note,
            **({"extra": to_jsonable(self.extra)} if self.extra else {}),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Comparison:
        return cls(
            figure=d["figure"],
            unit=d.get("unit", ""),
            baseline=d.get("baseline"),
            sdk=d.get("sdk"),
            baseline_label=d.get("baseline_label", "raw"),
            sdk_label=d.get("sdk_label", "agentsdk"),
            lower_is_better=d.get("lower_is_better", True),
            diff_target=d.get("diff_target"),
            sdk_target=d.get("sdk_target"),
            ratio_target=d.get("ratio_target"),
            note=d.get("note", ""),
            extra=d.get("extra", {}),
        )


COMPARISON_HEADERS = ("figure", "unit", "baseline", "agentsdk", "diff", "ratio", "target")


@dataclass
class Table:
    """An extra table of a section (e.g. a profile, per-run detail)."""

    title: str
    headers: Sequence[str]
    rows: list[Sequence[Any]]

    def render(self) -> str:
        return format_table(self.headers, self.rows, self.title)

    def to_json(self) -> dict[str, Any]:
        return {"title": self.title, "headers": list(self.headers), "rows": to_jsonable(self.rows)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Table:
        return cls(d.get("title", ""), d.get("headers", []), d.get("rows", []))


@dataclass
class Section:
    """The result of one benchmark: comparisons, extra tables, notes and raw data for the JSON.

    ``status`` is "ok", "missing" (module not there), "error" or "skipped".
    """

    name: str
    title: str
    comparisons: list[Comparison] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)
    status: str = "ok"
    seconds: float = 0.0

    def render(self) -> str:
        head = f"== {self.name}: {self.title}"
        if self.status != "ok":
            head += f"  [{self.status.upper()}]"
        if self.seconds:
            head += f"  ({self.seconds:.1f} s)"
        parts = [head]
        if self.comparisons:
            parts.append(format_table(COMPARISON_HEADERS, [c.row() for c in self.comparisons]))
        for t in self.tables:
            parts.append(t.render())
        for n in self.notes:
            parts.append(f"note: {n}")
        return "\n\n".join(parts)

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "title": self.title,
            "status": self.status,
            "seconds": round(self.seconds, 3),
            "comparisons": [c.to_json() for c in self.comparisons],
            "tables": [t.to_json() for t in self.tables],
            "notes": list(self.notes),
            "data": to_jsonable(self.data),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Section:
        return cls(
            name=d["name"],
            title=d.get("title", ""),
            comparisons=[Comparison.from_json(c) for c in d.get("comparisons", [])],
            tables=[Table.from_json(t) for t in d.get("tables", [])],
            notes=list(d.get("notes", [])),
            data=d.get("data", {}),
            status=d.get("status", "ok"),
            seconds=float(d.get("seconds", 0.0)),
        )


# --------------------------------------------------------------------------- JSON


def to_jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays, dataclass-like objects, tuples and non-finite floats to plain JSON."""
    if obj is None or isinstance(obj, bool | int | str):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set | frozenset):
        return [to_jsonable(v) for v in obj]
    to_json = getattr(obj, "to_json", None)
    if callable(to_json):
        return to_jsonable(to_json())
    tolist = getattr(obj, "tolist", None)  # numpy arrays and scalars
    if callable(tolist):
        return to_jsonable(tolist())
    if hasattr(obj, "__dataclass_fields__"):
        return {k: to_jsonable(getattr(obj, k)) for k in obj.__dataclass_fields__}
    return str(obj)


def write_json(path: str | os.PathLike[str], data: Any) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(to_jsonable(data), f, indent=2, ensure_ascii=False)
        f.write("\n")


def timed(fn: Callable[[], Any]) -> float:
    """Wall seconds of one call."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0
