"""The architecture holds (docs/architecture.md, section 2: layers as packages), and each check
would catch a breach: the import contracts of ``pyproject.toml`` (``[tool.importlinter]``), no
import circles between modules (imports inside functions and under ``TYPE_CHECKING`` included),
and no module above 450 lines (the numba kernels aside: a kernel is one long loop nest).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "sogm_service"
MAX_MODULE_LINES = 450
LONG_BY_NATURE = {"sogm_service/core/sevds/kernels.py"}  # numba kernels


def _lint_imports(cwd: Path, pythonpath: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    code = ("import sys; from importlinter.cli import lint_imports; "
            "sys.exit(lint_imports(no_cache=True, no_logo=True))")
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120)


def _copy_of_package(tmp_path: Path) -> Path:
    shutil.copytree(PACKAGE, tmp_path / "sogm_service",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path / "sogm_service"


def test_the_package_keeps_every_layer_contract() -> None:
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    proc = _lint_imports(ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"{len(contracts['contracts'])} kept, 0 broken" in proc.stdout


def test_a_forbidden_import_in_the_core_breaks_the_contract(tmp_path: Path) -> None:
    """A copy of the package whose core imports zenoh and the service fails the check."""
    victim = _copy_of_package(tmp_path) / "core" / "logodds.py"
    victim.write_text(victim.read_text() + "\n\ndef _leak() -> None:\n"
                      "    import zenoh  # noqa\n"
                      "    from sogm_service.service.server import server  # noqa\n")
    proc = _lint_imports(tmp_path, pythonpath=tmp_path)
    assert proc.returncode != 0
    assert "core is pure: no I/O libraries, nothing above it BROKEN" in proc.stdout
    assert "sogm_service.core.logodds -> zenoh" in proc.stdout


def _import_circles(root: Path) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan), in a child process so that
    the copy in ``root`` is the package grimp reads."""
    code = (
        "import json, sys, grimp\n"
        "g = grimp.build_graph('sogm_service', cache_dir=None)\n"
        "edges = {m: sorted(g.find_modules_directly_imported_by(m)) for m in g.modules}\n"
        "print(json.dumps(edges))\n")
    env = dict(os.environ, PYTHONPATH=str(root))
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True,
                          text=True, timeout=120, check=True)
    import json

    edges: dict[str, list[str]] = json.loads(proc.stdout)
    return _strongly_connected(edges)


def _strongly_connected(edges: dict[str, list[str]]) -> list[list[str]]:
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []
    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, []):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return groups




def test_no_import_circles() -> None:
    assert grimp.__version__  # the graph comes from import-linter's own import reader
    assert _import_circles(ROOT) == []


def test_an_import_circle_would_be_found(tmp_path: Path) -> None:
    """A type-only import of the tiled map from the tile module closes a circle in a copy."""
    victim = _copy_of_package(tmp_path) / "core" / "map" / "tile.py"
    text = victim.read_text()
    victim.write_text(text + "\n\nfrom typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
                      "    from sogm_service.core.map.tiles import TiledMap  # noqa\n")
    circles = _import_circles(tmp_path)
    assert any({"sogm_service.core.map.tile", "sogm_service.core.map.tiles"} <= set(group)
               for group in circles), circles


def _module_lines() -> dict[str, int]:
    return {str(p.relative_to(ROOT)): len(p.read_text().splitlines())
            for p in PACKAGE.rglob("*.py")}


def test_no_module_above_450_lines() -> None:
    long = {path: n for path, n in _module_lines().items()
            if n > MAX_MODULE_LINES and path not in LONG_BY_NATURE}
    assert long == {}, f"modules above {MAX_MODULE_LINES} lines: {long}"


def test_no_reference_to_the_history_of_the_work() -> None:
    """Code and tests say what the code does, not which issue or session added it."""
    pattern = re.compile(r"\bissues? #?\d+|\b[D]ESIGN\.md\b")  # [D]: no hit on this line
    hits = [f"{p.relative_to(ROOT)}:{i}" for folder in ("sogm_service", "tests")
            for p in (ROOT / folder).rglob("*.py")
            for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)
            and p != Path(__file__).resolve()]
    assert hits == []
