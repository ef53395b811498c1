"""The documentation site builds strictly, the README stays the short front door, and nothing in
the repository cites a design file outside it.

``mkdocs build --strict`` (with the link, anchor and omitted-file validation of ``mkdocs.yml``)
fails on any link that does not resolve and on any page left out of the nav.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.integration

yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
CI_RUN = ROOT / ".ci" / "run"
MAX_README_LINES = 200
# Assembled so that this file does not itself contain the strings it looks for.
FORBIDDEN = ("DESIGN" + ".md", "../" + "shared")
SCANNED = ("sogm_service", "tests", "docs", "deploy", "README.md", "pyproject.toml")


def _nav_pages(nav: Any) -> Iterator[str]:
    """Every page file named anywhere in a (nested) MkDocs nav."""
    if isinstance(nav, str):
        yield nav
    elif isinstance(nav, list):
        for item in nav:
            yield from _nav_pages(item)
    elif isinstance(nav, dict):
        for value in nav.values():
            yield from _nav_pages(value)


def _config() -> dict[str, Any]:
    loaded = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    assert isinstance(loaded, dict)
    return loaded


def _ci_test_line() -> str:
    """The command .ci/run runs: the line after its 'Keep this line identical' comment."""
    lines = CI_RUN.read_text().splitlines()
    marker = next(i for i, line in enumerate(lines) if "Keep this line identical" in line)
    return lines[marker + 1].strip()


def _quick_start_block() -> list[str]:
    """The lines of the first code block of the README's Quick start section."""
    lines = README.read_text().splitlines()
    start = lines.index("## Quick start") + 1
    body = [line for line in lines[start:] if line.strip()]
    assert body[0].startswith("```"), "the Quick start must open with its commands"
    end = body.index("```", 1)
    return body[1:end]


def test_mkdocs_build_is_strict_clean(tmp_path: Path) -> None:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=120, env=env, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "architecture" / "index.html").is_file()


def test_every_docs_page_is_in_the_nav() -> None:
    config = _config()
    assert config["theme"]["name"] == "material"
    assert config.get("strict") is True
    in_nav = set(_nav_pages(config["nav"]))
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert pages - in_nav == set(), "pages missing from the nav"
    assert in_nav - pages == set(), "nav entries without a page"


def test_readme_is_short_and_maps_every_page() -> None:
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    for page in DOCS.rglob("*.md"):
        assert f"(docs/{page.relative_to(DOCS).as_posix()}" in text, f"README omits {page.name}"


def test_readme_quick_start_runs_what_ci_runs() -> None:
    commands = _quick_start_block()
    assert len(commands) == 2
    assert commands[0].endswith(".venv/bin/sogm-service demo")
    assert commands[1] == _ci_test_line()


def _text_files() -> Iterator[Path]:
    for name in SCANNED:
        path = ROOT / name
        candidates = [path] if path.is_file() else sorted(path.rglob("*"))
        for candidate in candidates:
            if candidate.is_file() and "__pycache__" not in candidate.parts:
                yield candidate


def test_nothing_cites_files_outside_the_repository() -> None:
    offenders = []
    for path in _text_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # binary (pictures, test data)
        offenders += [f"{path.relative_to(ROOT)}: {needle}" for needle in FORBIDDEN
                      if needle in text]
    assert offenders == []
