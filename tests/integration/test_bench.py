"""The bench harness keeps working: ``sogm-service bench --quick`` writes every row.

Asserts the shape of the report only, never a speed: speed is what the bench measures, on a
shared machine where any timed assertion would be flaky.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from sogm_service.bench import core, registry

pytestmark = pytest.mark.integration

def _run(tmp_path: Path, *names: str) -> dict:
    out = tmp_path / "bench.json"
    proc = subprocess.run(
        [sys.executable, "-m", "sogm_service", "bench", *names, "--quick", "--json", str(out)],
        capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "| benchmark |" in proc.stdout
    return json.loads(out.read_text())


def _check_row(row: dict) -> None:
    assert row["target"], row
    assert not row["note"].startswith(("not available", "error")), row
    for key in ("ours", "baseline", "ratio"):
        assert isinstance(row[key], float) and row[key] > 0, (key, row)
    assert row["unit"] and row["baseline_name"], row
    assert row["passed"] in (True, False, None)


def _start(out: Path, names: list[str]) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "sogm_service", "bench", *names, "--quick", "--json", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_quick_bench_reports_every_row_with_positive_numbers(tmp_path: Path) -> None:
    # Every row, in two bench processes side by side: most quick rows wait on processes they
    # start (servers, routers, the demo), so two halves take about half the wall time of one
    # process (three took no less); the numbers of a smoke run on a shared machine are not
    # judged, only the report's shape.
    every = [b.name for b in registry()]
    parts = [every[0::2], every[1::2]]
    outs = [tmp_path / f"bench{k}.json" for k in range(2)]
    procs = [_start(out, names) for out, names in zip(outs, parts, strict=True)]
    try:
        texts = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)
    rows = []
    for proc, text, out in zip(procs, texts, outs, strict=True):
        assert proc.returncode == 0, text
        assert "| benchmark |" in text
        report = json.loads(out.read_text())
        assert report["quick"] is True
        assert report["machine"]["cores"] and report["machine"]["cpu"]
        rows += report["rows"]
    names = [r["name"] for r in rows]
    assert len(names) == len(every) == len(set(names))
    for row in rows:
        _check_row(row)


def test_names_select_and_unknown_names_are_refused(tmp_path: Path) -> None:
    report = _run(tmp_path, "fuse_aligned")
    assert [r["name"] for r in report["rows"]] == ["fuse_aligned_1024"]
    bad = subprocess.run([sys.executable, "-m", "sogm_service", "bench", "nope", "--quick"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "unknown benchmark" in bad.stderr


def test_table_marks_unavailable_and_report_only_rows() -> None:
    rows = [core.unavailable("x", "<= 1x", "not yet"),
            core.Row("y", 2.0, 1.0, "ms", 2.0, "report", None, "b")]
    text = core.table(rows)
    assert "| x | - | - | - | <= 1x | n/a |" in text
    assert "| y | 2.00 ms | 1.00 ms | 2.00x | report | report |" in text
