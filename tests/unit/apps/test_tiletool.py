"""``sogm-service tiles ls|export|import`` on real store directories."""

from __future__ import annotations

import argparse
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sogm_service.apps import render
from sogm_service.apps.tiletool import add_tiles_parser, build_parser, main, run_tiles
from sogm_service.core import logodds
from sogm_service.store.directory import QUARANTINE_DIR, DirectoryStore
from sogm_service.wire.tilefile import tile_file_name

T = 16
RES = 0.1  # 1.6 m tiles


def make_store(path: Path, tiles: dict[tuple[int, int], tuple[list[str], np.ndarray]],
               name: str = "lab") -> None:
    with DirectoryStore(path, name, RES, T) as store:
        for (i, j), (layers, data) in tiles.items():
            store.write(i, j, layers, data, 1700000000.0 + i)


def filled(n: int, value: int) -> np.ndarray:
    return np.full((n, T, T), value, dtype=np.int16)


def run(argv: list[str]) -> tuple[int, str]:
    out = io.StringIO()
    code = run_tiles(build_parser().parse_args(argv), out)
    return code, out.getvalue()


def test_ls_lists_every_tile_and_flags_bad_files(tmp_path: Path) -> None:
    make_store(tmp_path, {(0, 0): (["a", "b"], filled(2, 100)), (-1, 2): (["a"], filled(1, 0))})
    code, text = run(["ls", str(tmp_path)])
    assert code == 0
    lines = text.splitlines()
    assert len(lines) == 4 and lines[-1] == "2 tile(s), 0 bad"
    assert any("2: a,b" in line and "sogm_lab_r0.100_t16_i+0000_j+0000.tile" in line
               for line in lines)
    assert any(" -1 " in line and "2023-11-14 22:13:19" in line for line in lines)
    # Corrupt one payload: plain ls (headers) misses it, --verify finds it; neither moves it.
    path = tmp_path / tile_file_name("lab", RES, T, 0, 0)
    raw = bytearray(path.read_bytes())
    raw[-5] ^= 0xFF
    path.write_bytes(bytes(raw))
    assert run(["ls", str(tmp_path)])[0] == 0
    code, text = run(["ls", str(tmp_path), "--verify"])
    assert code == 1 and "BAD sogm_lab_r0.100_t16_i+0000_j+0000.tile: payload checksum" in text
    assert path.exists() and not (tmp_path / QUARANTINE_DIR).exists()


def test_export_npy_of_a_range_mosaics_tiles_and_layers(tmp_path: Path) -> None:
    store = tmp_path / "s"
    make_store(store, {(0, 0): (["a"], filled(1, 500)), (1, 0): (["b", "a"], filled(2, -700))})
    out = tmp_path / "region.npy"
    code, _ = run(["export", str(store), "--range", "0", "0", "1", "1", "--out", str(out)])
    assert code == 0
    data = np.load(out)
    side = json.loads((tmp_path / "region.npy.json").read_text())
    assert side["layers"] == ["a", "b"] and data.shape == (2, 2 * T, 2 * T)
    assert side["origin"] == [0.0, 0.0] and side["resolution"] == RES
    assert (data[0, :T, :T] == 500).all() and (data[1, :T, :T] == 0).all()  # b absent: unknown
    assert (data[:, :T, T:] == -700).all()
    assert (data[:, T:, :] == 0).all()  # tiles (0, 1), (1, 1) do not exist: unknown


def test_export_box_crops_to_cells(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(-3000, 3000, (1, T, T)).astype(np.int16)
    make_store(tmp_path / "s", {(0, 0): (["a"], a)})
    out = tmp_path / "box.npy"
    code, _ = run(["export", str(tmp_path / "s"), "--box", "0.2", "0.3", "0.6", "1.0",
                   "--out", str(out)])
    assert code == 0
    assert np.array_equal(np.load(out)[0], a[0, 3:10, 2:6])
    assert json.loads((tmp_path / "box.npy.json").read_text())["origin"] == pytest.approx(
        [0.2, 0.3])


def test_export_png_one_image_per_layer_with_unknown_tinted(tmp_path: Path) -> None:
    data = np.zeros((2, T, T), dtype=np.int16)
    data[0, :, : T // 2] = logodds.prob_to_fixed(0.999)  # left half occupied
    data[0, :, T // 2:] = logodds.prob_to_fixed(0.001)  # right half free
    data[1, 0, 0] = logodds.prob_to_fixed(0.999)  # one occupied cell, the rest unknown
    make_store(tmp_path / "s", {(2, 3): (["robot1/laser/obstacle", "person"], data)})
    out = tmp_path / "t.png"
    code, text = run(["export", str(tmp_path / "s"), "--tile", "2", "3", "--out", str(out)])
    assert code == 0
    first = cv2.imread(str(tmp_path / "t_robot1-laser-obstacle.png"))
    second = cv2.imread(str(tmp_path / "t_person.png"))
    assert first is not None and second is not None and first.shape == (T, T, 3)
    assert (first[:, 0] == 0).all() and (first[:, -1] == 255).all()  # black occ., white free
    unknown = np.array(render.UNKNOWN_BGR, dtype=np.uint8)
    assert (second[:-1] == unknown).all()  # distinct from any grey
    assert (second[-1, 0] == 0).all()  # cell (0, 0) is bottom-left: north up
    assert "wrote" in text


def test_export_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make_store(tmp_path / "s", {(0, 0): (["a"], filled(1, 1))})
    make_store(tmp_path / "s2", {(0, 0): (["a"], filled(1, 1))}, name="other")
    for p in (tmp_path / "s2").glob("*.tile"):
        p.rename(tmp_path / "s" / p.name)
    code, _ = run(["export", str(tmp_path / "s"), "--tile", "0", "0", "--out", "x.npy"])
    assert code == 2 and "several maps" in capsys.readouterr().err
    code, _ = run(["export", str(tmp_path / "s"), "--map", "lab", "--tile", "5", "5",
                   "--out", str(tmp_path / "x.npy")])
    assert code == 2 and "no readable tile" in capsys.readouterr().err
    code, _ = run(["export", str(tmp_path / "s"), "--map", "lab", "--tile", "0", "0",
                   "--layers", "zzz", "--out", str(tmp_path / "x.npy")])
    assert code == 2 and "no layer" in capsys.readouterr().err


def test_import_validates_copies_and_rejects_with_reasons(tmp_path: Path) -> None:
    src, dest = tmp_path / "src", tmp_path / "dest"
    make_store(src, {(0, 0): (["a"], filled(1, 11)), (1, 0): (["a"], filled(1, 22))})
    bad = src / tile_file_name("lab", RES, T, 1, 0)
    bad.write_bytes(bad.read_bytes()[:-7])
    (src / "junk.tile").write_bytes(b"not a tile")
    code, text = run(["import", str(src), "--into", str(dest)])
    assert code == 1
    assert "1 imported, 0 skipped, 2 rejected" in text
    assert "truncated" in text and "magic" in text
    assert bad.exists()  # the source is never touched
    with DirectoryStore(dest, "lab", RES, T) as store:
        assert list(store.index()) == [(0, 0)]
        tile = store.load(0, 0)
        assert tile is not None and (tile.data == 11).all()


def test_import_conflict_policies(tmp_path: Path) -> None:
    src, dest = tmp_path / "src", tmp_path / "dest"
    make_store(src, {(0, 0): (["a"], filled(1, 1))})  # stamp 1700000000
    with DirectoryStore(dest, "lab", RES, T) as store:
        store.write(0, 0, ["a"], filled(1, 2), 1600000000.0)  # older
    assert "1 skipped" in run(["import", str(src), "--into", str(dest)])[1]
    assert "1 imported" in run(["import", str(src), "--into", str(dest),
                                "--on-conflict", "newer"])[1]
    assert "1 skipped" in run(["import", str(src), "--into", str(dest),
                               "--on-conflict", "newer"])[1]  # not newer any more
    with DirectoryStore(dest, "lab", RES, T) as store:
        tile = store.load(0, 0)
        assert tile is not None and (tile.data == 1).all()


def test_import_refuses_a_store_in_use(tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    make_store(tmp_path / "src", {(0, 0): (["a"], filled(1, 1))})
    with DirectoryStore(tmp_path / "dest", "lab", RES, T):
        code, _ = run(["import", str(tmp_path / "src"), "--into", str(tmp_path / "dest")])
    assert code == 2 and "in use" in capsys.readouterr().err


def test_entry_points(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make_store(tmp_path, {(0, 0): (["a"], filled(1, 1))})
    assert main(["ls", str(tmp_path)]) == 0
    assert "1 tile(s)" in capsys.readouterr().out
    parser = argparse.ArgumentParser(prog="sogm-service")
    add_tiles_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["tiles", "ls", str(tmp_path)])
    assert args.command == "tiles" and run_tiles(args) == 0
