"""The package layering of DESIGN.md section 2 holds, and the check would catch a breach.

The contracts live in ``pyproject.toml`` (``[tool.importlinter]``) and are checked by
import-linter, which reads every import in the package, including those inside functions.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _lint_imports(cwd: Path, pythonpath: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    code = ("import sys; from importlinter.cli import lint_imports; "
            "sys.exit(lint_imports(no_cache=True, no_logo=True))")
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120)


def test_the_package_keeps_every_layer_contract() -> None:
    proc = _lint_imports(ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "5 kept, 0 broken" in proc.stdout


def test_a_forbidden_import_in_the_core_breaks_the_contract(tmp_path: Path) -> None:
    """A copy of the package whose core imports zenoh and the service fails the check."""
    shutil.copytree(ROOT / "sogm_service", tmp_path / "sogm_service",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    victim = tmp_path / "sogm_service" / "core" / "logodds.py"
    victim.write_text(victim.read_text() + "\n\ndef _leak() -> None:\n"
                      "    import zenoh  # noqa\n"
                      "    from sogm_service.service import server  # noqa\n")
    proc = _lint_imports(tmp_path, pythonpath=tmp_path)
    assert proc.returncode != 0
    assert "core is pure: no I/O libraries, nothing above it BROKEN" in proc.stdout
    assert "sogm_service.core.logodds -> zenoh" in proc.stdout
