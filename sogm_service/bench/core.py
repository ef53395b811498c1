"""Rows, timing, the registry and the report of the bench suite (no benchmark lives here).

Every figure is a ratio against a baseline measured in the same run: the machine is shared
(2 cores, other work on it), so absolute times drift between runs while a ratio of two
interleaved measurements mostly does not.  Absolute numbers are kept beside the ratio.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

Details = dict[str, float | str]


@dataclass
class Row:
    """One benchmark's result.  ``passed`` is None for report-only or unavailable rows."""

    name: str
    ours: float | None
    baseline: float | None
    unit: str
    ratio: float | None
    target: str
    passed: bool | None
    baseline_name: str = ""
    note: str = ""
    details: Details = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Benchmark:
    """A named benchmark: ``run(quick)`` returns its row."""

    name: str
    summary: str
    run: Callable[[bool], Row]


def unavailable(name: str, target: str, why: str) -> Row:
    return Row(name, None, None, "", None, target, None, note=f"not available: {why}")


def time_once(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def best_time(fn: Callable[[], object], repeats: int = 5) -> float:
    """The fastest of ``repeats`` calls, in seconds (a bound's cost without the noise)."""
    return min(time_once(fn) for _ in range(repeats))


def interleaved(ours: Callable[[], object], base: Callable[[], object], repeats: int,
                warmup: int = 2) -> tuple[list[float], list[float]]:
    """Seconds per call of both, alternating, so that load changes hit both alike."""
    for _ in range(warmup):
        base()
        ours()
    t_ours, t_base = [], []
    for _ in range(repeats):
        t_base.append(time_once(base))
        t_ours.append(time_once(ours))
    return t_ours, t_base


def median(xs: list[float]) -> float:
    return float(statistics.median(xs))


def percentile(xs: list[float], q: float) -> float:
    """Nearest-rank percentile (``q`` in 0..100); with few samples p99 is the maximum."""
    s = sorted(xs)
    k = max(0, min(len(s) - 1, round(q / 100.0 * len(s) + 0.5) - 1))
    return float(s[k])


def time_row(name: str, ours: list[float], base: list[float], limit: float,
             baseline_name: str, note: str = "") -> Row:
    """A row of median times in ms whose target is ``ours <= limit x baseline``."""
    m_ours, m_base = median(ours) * 1e3, median(base) * 1e3
    ratio = m_ours / m_base
    return Row(name, m_ours, m_base, "ms", ratio, f"<= {limit:g}x", ratio <= limit,
               baseline_name, note,
               {"repeats": float(len(ours)), "ours_min_ms": min(ours) * 1e3,
                "baseline_min_ms": min(base) * 1e3})


def machine() -> dict[str, str]:
    """What the numbers ran on (they mean little without it)."""
    import numpy as np

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem = ""
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        mem = f"{pages * size / 2**30:.1f} GiB"
    except (ValueError, OSError):
        pass
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return {"cpu": cpu, "cores": str(os.cpu_count()), "memory": mem,
            "python": platform.python_version(), "numpy": np.__version__,
            "platform": platform.platform(), "load_at_start": load,
            "zenoh": _version("eclipse-zenoh"), "numba": _version("numba"),
            "opencv": _version("opencv-contrib-python-headless")}


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


def _fmt(x: float | None) -> str:
    if x is None:
        return "-"
    if x == 0 or abs(x) >= 100:
        return f"{x:.0f}"
    if abs(x) >= 10:
        return f"{x:.1f}"
    if abs(x) >= 0.1:
        return f"{x:.2f}"
    return f"{x:.3g}"


def verdict(row: Row) -> str:
    if row.note.startswith("not available"):
        return "n/a"
    if row.passed is None:
        return "report"
    return "pass" if row.passed else "FAIL"


def table(rows: list[Row]) -> str:
    """A Markdown table (prints well in a terminal and pastes into README)."""
    head = ["benchmark", "ours", "baseline", "ratio", "target", "result"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        unit = f" {r.unit}" if r.unit else ""
        ours = _fmt(r.ours) + (unit if r.ours is not None else "")
        base = _fmt(r.baseline) + (unit if r.baseline is not None else "")
        ratio = "-" if r.ratio is None else f"{_fmt(r.ratio)}x"
        lines.append(f"| {r.name} | {ours} | {base} | {ratio} | {r.target} | {verdict(r)} |")
    return "\n".join(lines)


def notes(rows: list[Row]) -> str:
    return "\n".join(f"- {r.name}: baseline = {r.baseline_name or '-'}"
                     + (f"; {r.note}" if r.note else "") for r in rows)


def report(rows: list[Row], quick: bool, started: float) -> dict[str, Any]:
    return {"quick": quick, "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                          time.gmtime(started)),
            "duration_s": round(time.time() - started, 2), "machine": machine(),
            "rows": [r.as_dict() for r in rows]}


def write_json(path: str, data: dict[str, Any]) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=2)
        f.write("\n")
