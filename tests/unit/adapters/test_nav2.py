"""nav2 map files (adapters/nav2): written by the adapter, read back as map_server reads them
(an independent PGM reader here); files written by hand read with their scale mode.

Its ``read_pgm`` and ``map_server_trinary`` serve the integration test of nav2 maps too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
yaml = pytest.importorskip("yaml")


from sogm_service.adapters.nav2 import Nav2MapError, export_nav2, read_nav2  # noqa: E402
from sogm_service.core.geometry import GridGeometry, Pose2D  # noqa: E402


def read_pgm(path: Path) -> np.ndarray:
    """A plain P5 parser (header tokens, comments, maxval 255), independent of OpenCV."""
    data = path.read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    assert tokens[0] == b"P5" and tokens[3] == b"255"
    w, h = int(tokens[1]), int(tokens[2])
    pixels = np.frombuffer(data[pos + 1:pos + 1 + w * h], dtype=np.uint8)
    assert pixels.size == w * h
    return pixels.reshape(h, w)


def map_server_trinary(px: np.ndarray, occupied: float, free: float,
                        negate: int) -> np.ndarray:
    """nav2 map_server's rule for a grey image: occ = 1 - v/255 (negate 0), thresholds."""
    shade = px / 255.0
    occ = shade if negate else 1.0 - shade
    out = np.full(px.shape, -1, np.int8)
    out[occ > occupied] = 100
    out[occ < free] = 0
    return out


def test_export_nav2_is_read_as_map_server_reads_it(tmp_path: Path) -> None:
    # 4 columns x 3 rows of probabilities, row 0 at the smallest y
    probs = np.array([[0.9, 0.1, 0.5, 0.7],
                      [0.2, 0.5, 0.99, 0.0],
                      [0.5, 0.5, 0.3, 0.66]])
    geom = GridGeometry(0.05, 4, 3, Pose2D(-1.5, 2.25, 0.1))
    yml, pgm = export_nav2(tmp_path / "out", probs, geom, kind="probability")
    doc = yaml.safe_load(yml.read_text())
    assert doc["image"] == "map.pgm" and (yml.parent / doc["image"]) == pgm
    assert doc["mode"] == "trinary" and doc["negate"] == 0
    assert doc["resolution"] == 0.05 and doc["origin"] == [-1.5, 2.25, 0.1]
    assert doc["occupied_thresh"] == 0.65 and doc["free_thresh"] == 0.25
    px = read_pgm(pgm)
    assert px.shape == (3, 4)
    # map_server: image row r -> grid row height - 1 - r, so the image's top row is max y
    grid = map_server_trinary(px, doc["occupied_thresh"], doc["free_thresh"], doc["negate"])
    grid = grid[::-1]
    expect = np.where(probs >= 0.65, 100, np.where(probs <= 0.25, 0, -1))
    expect[probs == 0.5] = -1
    assert np.array_equal(grid, expect)
    # our own reader gives the same cells and geometry
    m = read_nav2(yml)
    assert np.array_equal(m.occupancy, expect)
    assert m.geometry == geom
    ism = m.ism(layer="prior")
    assert ism.encoding == "occupancy_i8" and np.array_equal(ism.array(), expect)
    # 2x2 blocks of the 4x3 grid: four, one of them (row 2, columns 0-1) all unknown
    chunks = m.ism_chunks(max_side=2, layer="prior")
    assert len(chunks) == 3 and all(c.width <= 2 and c.height <= 2 for c in chunks)
    assert (chunks[2].width, chunks[2].height) == (2, 1)
    corner = geom.subgrid(2, 2, 2, 1).origin
    assert (chunks[2].origin.x, chunks[2].origin.y) == (pytest.approx(corner.x),
                                                        pytest.approx(corner.y))
    assert np.array_equal(chunks[2].array(), expect[2:3, 2:4])


def test_read_nav2_scale_mode_negate_and_errors(tmp_path: Path) -> None:
    img = np.array([[0, 255, 128]], dtype=np.uint8)  # top row only
    (tmp_path / "m.pgm").write_bytes(b"P5\n3 1\n255\n" + img.tobytes())
    (tmp_path / "m.yaml").write_text(
        "image: m.pgm\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\nnegate: 1\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\nmode: scale\n")
    m = read_nav2(tmp_path / "m.yaml")
    # negate: white is occupied; 128 -> occ 0.502 -> (0.502-0.196)/(0.65-0.196)*100 = 67
    assert m.occupancy.tolist() == [[0, 100, round((128 / 255 - 0.196) / (0.65 - 0.196) * 100)]]
    (tmp_path / "bad.yaml").write_text("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n")
    with pytest.raises(Nav2MapError) as e:
        read_nav2(tmp_path / "bad.yaml")
    assert e.value.code == "non_positive_resolution"
    (tmp_path / "noimg.yaml").write_text("image: nope.pgm\nresolution: 1\norigin: [0, 0, 0]\n")
    with pytest.raises(Nav2MapError) as e:
        read_nav2(tmp_path / "noimg.yaml")
    assert e.value.code == "not_found"


def test_trinary_counts_say_what_nav2_can_plan_through() -> None:
    from sogm_service.adapters.nav2 import trinary_counts, trinary_pixels

    fixed = np.array([[0, -4000, -4000], [4000, 0, -100]], np.int16)  # -100: p = 0.475
    counts = trinary_counts(trinary_pixels(fixed, "fixed"))
    assert (counts.free, counts.occupied, counts.unknown) == (2, 1, 3)
    assert str(counts) == "2 free, 1 occupied, 3 unknown"
