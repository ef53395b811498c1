"""The configuration reference, generated from the settings models.

:func:`render` gives the Markdown of ``docs/configuration.md`` (one table per section, then the
limits); :func:`render_toml` gives ``deploy/sogm-service.toml`` (every field at its default,
its description as a comment).  Both read the models of :mod:`sogm_service.service.config`:
each field's description, its unit and, for a limit, the refusal code and counters that
:data:`sogm_service.wire.limits.LIMITS` records, so the pages cannot drift from the code.

``python -m sogm_service.service.config_reference`` writes both files; with ``--check`` it
writes nothing and exits 1 naming each file that differs from what it would write.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import textwrap
import types
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from sogm_service.service.config import ServiceConfig
from sogm_service.wire.limits import LIMITS

DOCS_PAGE = Path("docs/configuration.md")
DEPLOY_FILE = Path("deploy/sogm-service.toml")
REPO_ROOT = Path(__file__).resolve().parents[2]
REGENERATE = "python -m sogm_service.service.config_reference"

_ORDER = ("map", "ism", "ism.matching", "tiles", "storage", "store", "limits", "ros2", "nav2",
          "cluster", "zenoh")
"""The sections in the order the pages list them (the models' own order puts zenoh earlier)."""


@dataclass(frozen=True, slots=True)
class Section:
    """One table of the file: ``path`` is its dotted name ("" for the top level)."""

    path: str
    model: type[BaseModel]
    array: bool  # [[path]]: a list of tables

    @property
    def header(self) -> str:
        if not self.path:
            return "top-level fields"
        return f"[[{self.path}]]" if self.array else f"[{self.path}]"

    def fields(self) -> Iterator[tuple[str, FieldInfo]]:
        """The section's own fields (not the tables nested in it)."""
        for name, info in self.model.model_fields.items():
            if _table_of(info) is None:
                yield name, info


def _table_of(info: FieldInfo) -> tuple[type[BaseModel], bool] | None:
    """The model of a field that is a table of settings (its default a model, or a non-empty
    list of models), with whether it is an array of tables; None for a value field (a value
    may still be a model: the datum, unset by default, is an inline table)."""
    default = info.get_default(call_default_factory=True)
    if isinstance(default, BaseModel):
        return type(default), False
    if isinstance(default, list) and default and isinstance(default[0], BaseModel):
        return type(default[0]), True
    return None


def sections() -> list[Section]:
    """Every section of :class:`ServiceConfig`, found by walking it, in the pages' order."""
    found: list[Section] = []

    def walk(model: type[BaseModel], prefix: str) -> None:
        for name, info in model.model_fields.items():
            table = _table_of(info)
            if table is not None:
                path = f"{prefix}.{name}" if prefix else name
                found.append(Section(path, table[0], table[1]))
                walk(table[0], path)

    walk(ServiceConfig, "")
    found.sort(key=lambda s: _ORDER.index(s.path) if s.path in _ORDER else len(_ORDER))
    return [*found, Section("", ServiceConfig, False)]


# -- what a field shows -------------------------------------------------------------------------

def extra(info: FieldInfo) -> dict[str, Any]:
    """The field's ``json_schema_extra`` (unit, example, and a limit's refusal and counters)."""
    value = info.json_schema_extra
    return dict(value) if isinstance(value, dict) else {}


def unit(info: FieldInfo) -> str:
    return str(extra(info).get("unit", ""))


def toml_value(value: Any) -> str:
    """``value`` as a TOML literal."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str | Path):
        return json.dumps(str(value))
    if isinstance(value, BaseModel):
        return toml_value(value.model_dump())
    if isinstance(value, dict):
        if not value:
            return "{}"
        items = ", ".join(f"{_toml_key(k)} = {toml_value(v)}" for k, v in value.items())
        return "{ " + items + " }"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML literal for {value!r}")


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def type_text(annotation: Any) -> str:
    """A field's type in words: ``float``, ``list of string``, ``"off", "correct" or ...``."""
    origin, args = get_origin(annotation), get_args(annotation)
    if origin is Annotated:
        return type_text(args[0])
    if origin in (Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        text = " or ".join(type_text(a) for a in inner)
        return f"{text} (optional)" if len(inner) < len(args) else text
    if origin is Literal:
        words = [json.dumps(a) for a in args]
        return ", ".join(words[:-1]) + " or " + words[-1] if len(words) > 1 else words[0]
    if origin is list:
        return f"list of {type_text(args[0])}"
    if origin is dict:
        return f"table of {type_text(args[0])} -> {type_text(args[1])}"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "inline table {" + ", ".join(annotation.model_fields) + "}"
    names = {bool: "boolean", int: "integer", float: "float", str: "string", Path: "path"}
    return names.get(annotation, getattr(annotation, "__name__", str(annotation)))


def constraints(info: FieldInfo) -> list[str]:
    """The bounds pydantic checks, in words: ``> 0``, ``<= 100``, ``matching ^...$``."""
    parts: list[str] = []
    for meta in info.metadata:
        for attr, sign in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            bound = getattr(meta, attr, None)
            if bound is not None:
                parts.append(f"{sign} {_number(bound)}")
        pattern = getattr(meta, "pattern", None)
        if pattern is not None:
            parts.append(f"matching {pattern}")
    return parts


def _number(value: float) -> str:
    if isinstance(value, int) or float(value).is_integer():
        return str(int(value))
    return f"{value:g}"


def default_of(info: FieldInfo) -> Any:
    return info.get_default(call_default_factory=True)


def readable(value: Any, unit_name: str) -> str:
    """A big default in a reader's terms: ``128 MiB``, ``4096 x 4096``; "" when plain."""
    if isinstance(value, bool) or not isinstance(value, int):
        return ""
    if unit_name == "bytes" and value >= 1 << 20 and value % (1 << 20) == 0:
        return f"{value >> 20} MiB"
    side = round(value ** 0.5)
    if unit_name == "cells" and value >= 1 << 20 and side * side == value:
        return f"{side} x {side}"
    return ""


# -- the Markdown page ---------------------------------------------------------------------------

def _cell(text: str) -> str:
    """Text safe in a Markdown table cell (no HTML tags, no column breaks)."""
    for plain, escaped in (("&", "&amp;"), ("<", "&lt;"), (">", "&gt;"), ("|", "\\|"),
                           ("*", "\\*"), ("\n", " ")):
        text = text.replace(plain, escaped)
    return text


def _code(text: str) -> str:
    return "`" + text.replace("|", "\\|") + "`"


def _docstring(model: type[BaseModel]) -> str:
    """A section model's docstring as one Markdown paragraph (reST roles as code)."""
    text = " ".join((model.__doc__ or "").split())
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def _default_cell(info: FieldInfo) -> str:
    value = default_of(info)
    if value is None:
        example = extra(info).get("example")
        return "unset" + (f" (e.g. {_code(toml_value(example))})" if example is not None
                          else "")
    hint = readable(value, unit(info))
    return _code(toml_value(value)) + (f" ({hint})" if hint else "")


def _type_cell(info: FieldInfo) -> str:
    parts = [_cell(type_text(info.annotation))]
    for bound in constraints(info):
        word, _, pattern = bound.partition("matching ")
        parts.append(f"matching {_code(pattern)}" if not word and pattern else _cell(bound))
    return ", ".join(parts)


def _section_table(section: Section) -> list[str]:
    lines = [f"## {section.header}", ""]
    intro = _docstring(section.model)
    if intro:
        lines += [intro, ""]
    lines += ["| field | type | unit | default | description |", "|---|---|---|---|---|"]
    for name, info in section.fields():
        lines.append(f"| `{name}` | {_type_cell(info)} | {_cell(unit(info))} | "
                     f"{_default_cell(info)} | {_cell(info.description or '')} |")
    return [*lines, ""]


def limit_fields() -> list[tuple[str, FieldInfo]]:
    """Every limit's field by its dotted path (``limits.max_ism_cells``): the fields that carry
    a refusal code (possibly none) in their ``json_schema_extra``, in the order of
    :data:`~sogm_service.wire.limits.LIMITS`."""
    found = {(f"{s.path}.{name}" if s.path else name): info
             for s in sections() for name, info in s.fields() if "refused_as" in extra(info)}
    rank = {path: k for k, path in enumerate(LIMITS)}
    return sorted(found.items(), key=lambda item: rank.get(item[0], len(rank)))


def _limits_table() -> list[str]:
    lines = ["## Limits", "", *textwrap.wrap(
        "Every input is priced from its header before any work, and refused with a code when "
        "it is over a limit; a refusal changes nothing (no tile, no layer, no robot). ISM "
        "refusals are counted in `stats.rejected[<code>]` (and `isms_rejected`); poses in "
        "`poses_rejected` and `poses_rejected_<code>`; queries in `query_errors_<code>`. Each "
        "refusal is logged in one line, at most one a second per reason, attacker strings cut "
        "to `log_text_chars`. Query parameters that are not numbers, NaN or infinite are "
        "`bad_parameter`; every finite number is priced (`x=1e308` is `out_of_world`, "
        "`width=1e308` or `resolution=1e-300` is `window_too_large`). A limit of `[limits]` "
        "is named by its field; the others by their section.", 96, break_on_hyphens=False),
        "",
        "| limit | default | unit | refused as | what it bounds | stats counter |",
        "|---|---|---|---|---|---|"]
    for path, info in limit_fields():
        name = path.removeprefix("limits.")
        ex = extra(info)
        refused = _code(ex["refused_as"]) if ex["refused_as"] else "(not refused)"
        counters = ", ".join(_code(c) for c in ex.get("counters", ()))
        lines.append(f"| `{name}` | {_default_cell(info)} | {_cell(unit(info))} | {refused} | "
                     f"{_cell(info.description or '')} | {counters} |")
    return [*lines, ""]


_INTRO = f"""\
# Configuration

`sogm-service serve --config FILE.toml` reads a TOML file. Every field has a default, so no
file is needed, and a file holds only the fields it changes. Unknown fields are an error and
values are strict (`resolution = "0.1"`, a string, is refused), so a typo fails at start: a bad
file stops the server before it opens a session, with the field and the reason, exit status 2:

```
sogm-service: serve: invalid config bad.toml: map.eps0: Input should be less than 0.5
```

`deploy/sogm-service.toml` lists every field at its default, its description as a comment:
a starting point to copy and edit.

This page and that file are generated from the settings models
(`sogm_service/service/config.py`, the limits' values in `sogm_service/wire/limits.py`) by
`{REGENERATE}`; a test keeps them current.
"""


def render() -> str:
    """The Markdown of ``docs/configuration.md``."""
    lines = [_INTRO]
    for section in sections():
        lines += _section_table(section)
    lines += _limits_table()
    return "\n".join(lines).rstrip("\n") + "\n"


# -- the example TOML file ---------------------------------------------------------------------

_TOML_HEADER = f"""\
# sogm-service configuration: every field, with its default.  `sogm-service serve` with no
# --config uses exactly these values.  Unknown fields are an error (typos fail at start).
# Generated from the settings models by `{REGENERATE}`.
"""


def _comment(text: str, width: int = 100) -> list[str]:
    return textwrap.wrap(text, width, initial_indent="# ", subsequent_indent="# ",
                         break_on_hyphens=False, break_long_words=False)


def _toml_field(name: str, info: FieldInfo) -> list[str]:
    text = info.description or ""
    refused = extra(info).get("refused_as")
    if refused:
        text += f" Over it: {refused}."
    lines = _comment(text)
    value = default_of(info)
    if value is None:
        example = extra(info).get("example")
        return [*lines, f"# {name} = {toml_value(example)}" if example is not None
                else f"# {name} ="]
    return [*lines, f"{name} = {toml_value(value)}"]


def render_toml() -> str:
    """The text of ``deploy/sogm-service.toml``: top-level fields first (TOML wants them
    before any table), then every section."""
    ordered = sections()
    ordered = [ordered[-1], *ordered[:-1]]
    lines = [_TOML_HEADER]
    for section in ordered:
        if section.path:
            lines += [*_comment(_docstring(section.model).replace("`", "")), section.header]
        for name, info in section.fields():
            lines += _toml_field(name, info)
        lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"


# -- the command ---------------------------------------------------------------------------------

def outputs() -> dict[Path, str]:
    """Each generated file (relative to the repository) and its text."""
    return {DOCS_PAGE: render(), DEPLOY_FILE: render_toml()}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=REGENERATE.removeprefix("python -m "),
                                     description="Write (or --check) docs/configuration.md "
                                                 "and deploy/sogm-service.toml.")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 if a checked-in file differs")
    parser.add_argument("--root", type=Path, default=REPO_ROOT,
                        help="the repository (default: the one this module is in)")
    args = parser.parse_args(argv)
    stale: list[Path] = []
    for rel, text in outputs().items():
        path = args.root / rel
        current = path.read_text(encoding="utf-8") if path.exists() else None
        if current == text:
            continue
        if args.check:
            stale.append(rel)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
            print(f"wrote {rel}")
    for rel in stale:
        print(f"{rel} differs from the settings models; regenerate it with `{REGENERATE}`",
              file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
