"""The configuration reference is generated from the settings models and kept current."""

from __future__ import annotations

from pathlib import Path

import pytest

from sogm_service.service import config_reference as ref
from sogm_service.service.config import LimitSettings, ServiceConfig, StorageSettings
from sogm_service.wire import limits

ROOT = Path(__file__).resolve().parents[3]
UNIT_OF_SUFFIX = {"_m": "m", "_s": "s", "_mb": "MB", "_deg": "deg", "_rad": "rad",
                  "_cells": "cells", "_bytes": "bytes", "_tiles": "tiles"}


def _section_text(page: str, header: str) -> str:
    """The part of the page from the section's heading to the next one."""
    start = page.index(f"\n## {header}\n")
    end = page.find("\n## ", start + 1)
    return page[start:end if end >= 0 else None]


def test_checked_in_page_is_the_rendered_one() -> None:
    checked_in = (ROOT / ref.DOCS_PAGE).read_text(encoding="utf-8")
    assert checked_in == ref.render(), (
        f"{ref.DOCS_PAGE} is stale: regenerate it with `{ref.REGENERATE}`")


def test_sections_are_every_table_of_the_config_in_the_documented_order() -> None:
    headers = [s.header for s in ref.sections()]
    assert headers == ["[map]", "[[ism]]", "[ism.matching]", "[tiles]", "[storage]", "[store]",
                       "[limits]", "[ros2]", "[nav2]", "[cluster]", "[zenoh]", "top-level fields"]
    top = {name for name, _ in ref.Section("", ServiceConfig, False).fields()}
    assert top == {"pose_keys", "prefix", "log_level"}


def test_every_field_has_a_description_and_a_row_on_the_page() -> None:
    page = ref.render()
    count = 0
    for section in ref.sections():
        text = _section_text(page, section.header)
        for name, info in section.fields():
            assert info.description, f"{section.header} {name} has no description"
            row = next((line for line in text.splitlines()
                        if line.startswith(f"| `{name}` |")), None)
            assert row is not None, f"{section.header} {name} is not on the page"
            assert info.description.split()[0] in row
            count += 1
    assert count >= 80  # every section's fields, not an empty walk


def test_fields_named_with_a_unit_carry_that_unit() -> None:
    for section in ref.sections():
        for name, info in section.fields():
            for suffix, unit in UNIT_OF_SUFFIX.items():
                if name.endswith(suffix):
                    assert ref.unit(info) == unit, f"{section.path}.{name}"


def test_the_limits_table_has_every_limit_with_its_default_from_wire_limits() -> None:
    table = _section_text(ref.render(), "Limits")
    fields = dict(ref.limit_fields())
    assert set(fields) == set(limits.LIMITS)
    for path, lim in limits.LIMITS.items():
        section, name = path.split(".")
        model = {"limits": LimitSettings, "storage": StorageSettings}[section]
        assert model.model_fields[name].default == lim.default, path
        shown = path.removeprefix("limits.")
        row = next(line for line in table.splitlines() if line.startswith(f"| `{shown}` |"))
        cells = [c.strip() for c in row.strip("|").split(" | ")]
        assert cells[1].startswith(f"`{ref.toml_value(lim.default)}`"), row
        assert cells[2] == lim.unit
        assert cells[3] == (f"`{lim.refused_as}`" if lim.refused_as else "(not refused)")
        assert cells[4] == lim.bounds
        assert all(f"`{c}`" in cells[5] for c in lim.counters)


def test_the_limits_that_refuse_name_the_codes_admission_raises() -> None:
    codes = {lim.refused_as for lim in limits.LIMITS.values()} - {""}
    assert codes == {"too_large", "out_of_world", "too_many_layers", "too_many_robots",
                     "name_too_long", "memory_budget", "window_too_large", "reply_too_large",
                     "busy"}


def test_check_names_the_stale_file_and_writing_makes_it_current(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert ref.main(["--check", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert str(ref.DOCS_PAGE) in err and str(ref.DEPLOY_FILE) in err and ref.REGENERATE in err
    assert ref.main(["--root", str(tmp_path)]) == 0
    assert (tmp_path / ref.DOCS_PAGE).read_text(encoding="utf-8") == ref.render()
    assert ref.main(["--check", "--root", str(tmp_path)]) == 0
    (tmp_path / ref.DEPLOY_FILE).write_text("prefix = \"other\"\n", encoding="utf-8")
    assert ref.main(["--check", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert str(ref.DEPLOY_FILE) in err and str(ref.DOCS_PAGE) not in err
