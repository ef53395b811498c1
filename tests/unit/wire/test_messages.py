"""The committed JSON Schemas in schemas/ are what the wire models generate (no drift).

Regenerate after changing a model:
``.venv/bin/python -c "from pathlib import Path; from sogm_service import codec;
codec.write_schemas(Path('schemas'))"``
"""

from __future__ import annotations

import json
from pathlib import Path

from sogm_service.wire import codec
from sogm_service.wire.codec import SCHEMA_MODELS

SCHEMAS = Path(__file__).resolve().parents[3] / "schemas"


def test_committed_schemas_are_up_to_date() -> None:
    assert codec.stale_schemas(SCHEMAS) == []


def test_every_wire_model_has_a_schema_file() -> None:
    names = {getattr(m, "schema_name", "") or m.__name__ for m in SCHEMA_MODELS}
    assert len(names) == len(SCHEMA_MODELS)  # no two models share a file
    for name in names:
        schema = json.loads((SCHEMAS / f"{name}.json").read_text(encoding="utf-8"))
        assert schema["$id"].endswith(f"/{name}.json")
        assert schema["type"] == "object" and schema["properties"]


def test_stale_schemas_detects_drift(tmp_path: Path) -> None:
    written = codec.write_schemas(tmp_path)
    assert codec.stale_schemas(tmp_path) == []
    ism = tmp_path / "ism.json"
    assert ism in written
    ism.write_text(ism.read_text(encoding="utf-8").replace('"width"', '"widht"'),
                   encoding="utf-8")
    (tmp_path / "pose.json").unlink()
    assert sorted(codec.stale_schemas(tmp_path)) == ["ism", "pose"]


def test_ism_schema_documents_the_required_fields() -> None:
    schema = json.loads((SCHEMAS / "ism.json").read_text(encoding="utf-8"))
    assert set(schema["required"]) == {"resolution", "width", "height", "encoding", "data"}
    assert set(schema["properties"]["encoding"]["enum"]) == {
        "occupancy_i8", "prob_u8", "prob_f32", "prob_u8_v2"}
    # Versioned: prob_u8_v2 and NaN-as-unknown came with schema version 2, zstd data with 3
    # (documented there).
    assert schema["x-sogm-schema-version"] == 3
    assert "255 = unknown" in schema["properties"]["encoding"]["description"]
    assert "schema version 3" in schema["properties"]["compression"]["description"]
