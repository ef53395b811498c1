"""The paper's evaluation driver on small synthetic scenes (the simulator has its own tests)."""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from sogm_service.apps import cli
from sogm_service.eval import scenes
from sogm_service.eval import segmentation as ev

CLASSES = ("unknown", "floor", "table", "obstacle")


def synthetic_scene(seed: int) -> scenes.Scene:
    """48x48 room: unknown border, floor, one table and one obstacle, three noisy layers."""
    rng = np.random.default_rng(seed)
    cls = np.zeros((48, 48), np.uint8)
    cls[4:44, 4:44] = 1
    r, c = rng.integers(8, 22, size=2)
    cls[r:r + 14, c:c + 12] = 2
    cls[36:40, 8 + seed:12 + seed] = 3
    p = np.full((3, 48, 48), 0.5, np.float32)
    inside = cls > 0
    for layer, k in enumerate((3, 1, 2)):  # obstacle, floor, table layers
        p[layer][inside] = np.where(cls[inside] == k, 0.9, 0.1)
    p += rng.normal(0.0, 0.04, p.shape).astype(np.float32)
    return scenes.Scene.build(f"syn{seed}", ["obstacle", "floor", "table"], p, cls, CLASSES)


@pytest.fixture(scope="module")
def result(tmp_path_factory: pytest.TempPathFactory) -> ev.EvaluationResult:
    out = tmp_path_factory.mktemp("eval")
    return ev.run_supercell_evaluation(out, scenes=2, seed=1, quick=True, progress=False,
                                       scene_factory=synthetic_scene, blocks=(8, 16), rooms=1,
                                       intel=False)


def test_gt_segments_are_connected_components_per_class() -> None:
    cls = np.array([[0, 0, 1], [1, 0, 1]])
    seg = scenes.gt_segments(cls)
    # class 0: one piece; class 1: (0,2)-(1,2) and the lone (1,0) -> three segments.
    assert len(np.unique(seg)) == 3
    assert seg[0, 2] == seg[1, 2] != seg[1, 0]
    assert seg[0, 0] == seg[0, 1] == seg[1, 1]


def test_outputs_are_written(result: ev.EvaluationResult) -> None:
    names = {p.name for p in result.files}
    assert {"results.csv", "results.md", "segmentations.png", "rooms.csv"} <= names
    assert {f"{m}.png" for m in ev.METRICS} <= names
    for p in result.files:
        assert p.exists() and p.stat().st_size > 0
    fig = cv2.imread(str(result.out_dir / "segmentations.png"))
    assert fig is not None and fig.shape[1] > 7 * 48  # ground truth + six algorithms


def test_csv_has_every_algorithm_scene_and_count(result: ev.EvaluationResult) -> None:
    with (result.out_dir / "results.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(ev.ALGORITHMS) * 2 * 2
    assert {r["algorithm"] for r in rows} == set(ev.ALGORITHMS)
    assert {r["scene"] for r in rows} == {"syn1", "syn2"}
    for r in rows:
        for m in ev.METRICS:
            assert 0.0 <= float(r[m]) <= 1.0
    md = (result.out_dir / "results.md").read_text()
    for alg in ev.ALGORITHMS:
        assert f"| {alg} |" in md


def test_sevds_beats_a_plain_grid_on_clean_scenes(result: ev.EvaluationResult) -> None:
    # The synthetic objects do not sit on the 8-cell grid; the energy criterion must follow
    # their edges, so its boundary recall beats the untouched initial grid's.
    scene = synthetic_scene(1)
    grid = (np.arange(48)[:, None] // 8) * 6 + np.arange(48)[None, :] // 8
    grid_br = ev.metrics.boundary_recall(grid, scene.segments)
    row = next(r for r in result.rows
               if r["algorithm"] == "SEVDS-E" and r["scene"] == "syn1" and r["block"] == 8)
    assert row["br"] > grid_br


def test_tuning_keeps_the_best_parameter_set(result: ev.EvaluationResult) -> None:
    scenes = [synthetic_scene(1), synthetic_scene(2)]
    grid = ev.parameter_grids(quick=True)["SEVDS-E"]
    scores = []
    for p in grid:
        per_scene = []
        for s in scenes:
            lab = ev.RUNNERS["SEVDS-E"](s.stack, 8, p)
            per_scene.append(1.0 - ev.metrics.boundary_recall(lab, s.segments)
                             + ev.metrics.undersegmentation_error(lab, s.segments))
        scores.append(float(np.mean(per_scene)))
    assert result.chosen[("SEVDS-E", 8)] == grid[int(np.argmin(scores))]


def test_cli_parser_and_main(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                             capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    ev.add_arguments(parser)
    args = parser.parse_args(["--out", str(tmp_path), "--scenes", "2", "--seed", "5", "--quick"])
    assert (args.out, args.scenes, args.seed, args.quick) == (tmp_path, 2, 5, True)
    calls = []

    def fake_run(out: Path, **kw: object) -> ev.EvaluationResult:
        calls.append((out, kw))
        return ev.EvaluationResult(Path(out), [], "table")

    monkeypatch.setattr(ev, "run_supercell_evaluation", fake_run)
    assert cli.main(["eval", "supercells", "--out", str(tmp_path), "--scenes", "3"]) == 0
    assert calls[0][1]["scenes"] == 3 and calls[0][1]["quick"] is False
    assert cli.main(["eval", "supercells", "--scenes", "0"]) == 2
    assert cli.main(["eval", "supercells", "--rooms", "-1"]) == 2
    assert calls[0][1]["rooms"] == 4 and calls[0][1]["intel"] is True
    with pytest.raises(SystemExit) as refused:
        cli.main(["eval", "nothing"])
    assert refused.value.code == 2
    assert "sogm-service:" in capsys.readouterr().err
