"""The paper's evaluation (section IV): SEVDS against OpenCV's superpixels on table-top SOGMs.

``sogm-service eval supercells [--out DIR] [--scenes N] [--rooms N] [--no-intel] [--seed S]
[--quick]`` runs
:func:`run_supercell_evaluation`:

1. **Scenes.**  ``scenes`` randomised table-top rooms (:func:`sogm_service.sim.worlds.
   tabletop_world`, seeds ``seed, seed + 1, ...``; ground-truth classes unknown / floor / table /
   obstacle), mapped by the simulated tilted laser and semantic camera
   (:func:`sogm_service.sim.offline.map_world`) into an N-layer SOGM.  As in the paper the SOGM
   stack is the multi-channel input of every algorithm.
2. **Algorithms.**  SEVDS with both move criteria (``SEVDS`` = the paper's receiver rule
   "D(c_hat) < D(c)", ``SEVDS-E`` = the total-energy variant), and OpenCV's SEEDS, SLIC, SLICO
   and LSC.  OpenCV gets the stack as an 8-bit image ``round(255 p)`` (SEEDS needs integers).
3. **Matched counts and tuning.**  Superpixel counts follow SEVDS's initial grid: block edges
   ``8, 12, ..., 32`` cells (the paper's rule of thumb is 8); SEEDS is asked for the count that
   makes its number of superpixels nearest SEVDS's (:func:`sogm_service.eval.roomeval.
   seeds_request`: it rounds a request to its own block grid), SLIC / SLICO / LSC get the region
   size of the same edge.  At every count each algorithm runs a small grid of its
   own parameters and keeps the set minimising the scene mean of ``(1 - BR) + UE`` (Stutz et al.;
   one parameter set for all scenes, not one per scene).
4. **Metrics** (:mod:`sogm_service.eval.metrics`): Pureness (Eq. 12, on the classes), ICV and
EV (on the
   probability stack), UE and BR (on ground-truth segments: the 4-connected components of the
   classes).
5. **Outputs** in ``out_dir``: ``results.csv`` (every algorithm, scene and count with the chosen
   parameters), ``results.md`` (tables: at the paper's 8-cell rule, and the mean over counts),
   ``<metric>.png`` (each metric over the number of superpixels, paper Fig. 12-16) and
   ``segmentations.png`` (paper Fig. 11: class-majority colouring on top, boundaries in red below).
6. **Room maps** (``rooms`` of them, :mod:`sogm_service.eval.roomeval`): labelled room maps,
   SEVDS's defaults against tuned SEEDS at equal count (UE, BR, compactness, time), in
   ``rooms.csv`` and a third table of ``results.md``; the Intel replay's compactness, node
   evidence and time (unless ``--no-intel``) in ``intel.csv`` and a fourth.

The figures are drawn by :mod:`sogm_service.eval.figures`.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core.sevds.segment import SevdsParams, sevds
from sogm_service.eval import metrics
from sogm_service.eval.figures import metric_plots, segmentation_figure
from sogm_service.eval.metrics import METRICS
from sogm_service.eval.roomeval import (
    SEEDS_GRID,
    SEEDS_QUICK,
    intel_markdown,
    intel_rows,
    intel_stack,
    rooms_markdown,
    run_room_evaluation,
    run_seeds,
    write_rows,
)
from sogm_service.eval.scenes import Labels, Scene, tabletop_scene

Params = dict[str, float | int | str]

ALGORITHMS: tuple[str, ...] = ("SEVDS", "SEVDS-E", "SEEDS", "SLIC", "SLICO", "LSC")
BLOCKS_FULL: tuple[int, ...] = (8, 12, 16, 20, 24, 28, 32)
BLOCKS_QUICK: tuple[int, ...] = (8, 16, 32)
REFERENCE_BLOCK = 8  # the paper's rule of thumb: the smallest object, 8 cells


@dataclass
class EvaluationResult:
    """What one evaluation run produced (``rows``: one dict per algorithm, scene and count)."""

    out_dir: Path
    rows: list[dict[str, Any]]
    markdown: str
    files: list[Path] = field(default_factory=list)
    chosen: dict[tuple[str, int], Params] = field(default_factory=dict)
    seconds: float = 0.0


# --------------------------------------------------------------------------- algorithms


def _to_u8(stack: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
    """``(N, H, W)`` probabilities -> ``(H, W, N)`` 8-bit image for OpenCV."""
    return np.ascontiguousarray(np.rint(stack.transpose(1, 2, 0) * 255.0).astype(np.uint8))


def _run_sevds(criterion: str) -> Callable[[npt.NDArray[np.float32], int, Params], Labels]:
    def run(stack: npt.NDArray[np.float32], block: int, p: Params) -> Labels:
        # The paper's rule runs as the paper has it, without the default's doorway term.
        params = SevdsParams(block_size=block, levels=3, bins=int(p["bins"]), iterations=4,
                             gamma=float(p["gamma"]), criterion=criterion,  # type: ignore[arg-type]
                             doorway=SevdsParams().doorway if criterion == "energy" else 0.0)
        return sevds(stack, params).labels
    return run


def _run_seeds(stack: npt.NDArray[np.float32], block: int, p: Params) -> Labels:
    _, h, w = stack.shape
    return run_seeds(stack, -(-h // block) * -(-w // block), p)  # SEVDS's count


def _run_slic(kind: int) -> Callable[[npt.NDArray[np.float32], int, Params], Labels]:
    def run(stack: npt.NDArray[np.float32], block: int, p: Params) -> Labels:
        sp = cv2.ximgproc.createSuperpixelSLIC(_to_u8(stack), kind, block, float(p["ruler"]))
        sp.iterate(10)
        sp.enforceLabelConnectivity(25)
        return np.asarray(sp.getLabels(), np.int32)
    return run


def _run_lsc(stack: npt.NDArray[np.float32], block: int, p: Params) -> Labels:
    sp = cv2.ximgproc.createSuperpixelLSC(_to_u8(stack), block, float(p["ratio"]))
    sp.iterate(10)
    sp.enforceLabelConnectivity(25)
    return np.asarray(sp.getLabels(), np.int32)


def _grid(**axes: Sequence[float | int]) -> list[Params]:
    keys = list(axes)
    return [dict(zip(keys, vals, strict=True)) for vals in itertools.product(*axes.values())]


def parameter_grids(quick: bool = False) -> dict[str, list[Params]]:
    """The parameter sets tried per algorithm (a small grid each; ``quick`` shrinks it)."""
    if quick:
        return {"SEVDS": _grid(gamma=[0.0, 0.05], bins=[5]),
                "SEVDS-E": _grid(gamma=[0.0, 0.05], bins=[5]),
                "SEEDS": _grid(levels=[3], prior=[2], bins=[5]),
                "SLIC": _grid(ruler=[10.0]), "SLICO": _grid(ruler=[10.0]),
                "LSC": _grid(ratio=[0.075])}
    # SLICO adapts its compactness itself (the ruler is ignored), so it has nothing to tune.
    return {"SEVDS": _grid(gamma=[0.0, 0.005, 0.02, 0.1], bins=[5, 10, 20]),
            "SEVDS-E": _grid(gamma=[0.0, 0.01, 0.05, 0.2], bins=[5, 10, 20]),
            "SEEDS": _grid(levels=[3, 4], prior=[0, 2, 5], bins=[3, 5, 8]),
            "SLIC": _grid(ruler=[5.0, 10.0, 20.0, 40.0]), "SLICO": _grid(ruler=[10.0]),
            "LSC": _grid(ratio=[0.01, 0.025, 0.075, 0.15])}


RUNNERS: dict[str, Callable[[npt.NDArray[np.float32], int, Params], Labels]] = {
    "SEVDS": _run_sevds("distribution"),
    "SEVDS-E": _run_sevds("energy"),
    "SEEDS": _run_seeds,
    "SLIC": _run_slic(cv2.ximgproc.SLIC),
    "SLICO": _run_slic(cv2.ximgproc.SLICO),
    "LSC": _run_lsc,
}


# --------------------------------------------------------------------------- tuning


class _Progress:
    """A tqdm bar on stderr with the time left (a line every 10 s when not a terminal)."""

    def __init__(self, total: int, enabled: bool) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=max(1, total), desc="eval supercells", file=sys.stderr,
                        disable=not enabled,
                        mininterval=0.25 if sys.stderr.isatty() else 10.0)

    def step(self, what: str) -> None:
        self.bar.set_postfix_str(what[:40], refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def _objective(labels: Labels, scene: Scene) -> float:
    """Stutz et al.'s tuning target ``(1 - BR) + UE`` on the ground-truth segments."""
    seg = scene.segments
    return (1.0 - metrics.boundary_recall(labels, seg)) + metrics.undersegmentation_error(
        labels, seg)


def _tune(alg: str, block: int, scenes: Sequence[Scene], grid: list[Params],
          progress: _Progress) -> tuple[Params, list[Labels]]:
    """The parameter set with the lowest scene-mean objective, and its label images."""
    if not grid:
        raise ValueError(f"empty parameter grid for {alg}")
    best: tuple[float, Params, list[Labels]] | None = None
    for p in grid:
        labels = [RUNNERS[alg](s.stack, block, p) for s in scenes]
        score = float(np.mean([_objective(lab, s) for lab, s in zip(labels, scenes,
                                                                    strict=True)]))
        progress.step(f"{alg} block {block} {p}")
        if best is None or score < best[0]:
            best = (score, p, labels)
    assert best is not None  # the grid is not empty
    return best[1], best[2]


def _rows_for(alg: str, block: int, params: Params, labels: list[Labels],
              scenes: Sequence[Scene]) -> Iterator[dict[str, Any]]:
    for lab, scene in zip(labels, scenes, strict=True):
        m = metrics.all_metrics(lab, scene.stack, scene.classes, scene.segments)
        yield {"algorithm": alg, "scene": scene.name, "block": block,
               "superpixels": len(np.unique(lab)),
               "params": " ".join(f"{k}={v}" for k, v in params.items()), **m}


# --------------------------------------------------------------------------- outputs


def _mean_over(rows: list[dict[str, Any]], key: str) -> dict[str, dict[str, float]]:
    """``{algorithm: {name: mean over its rows}}`` for the five metrics and ``key``."""
    out: dict[str, dict[str, float]] = {}
    for alg in dict.fromkeys(r["algorithm"] for r in rows):
        sel = [r for r in rows if r["algorithm"] == alg]
        out[alg] = {m: float(np.mean([r[m] for r in sel])) for m in (*METRICS, key)}
    return out


def markdown_tables(rows: list[dict[str, Any]], reference_block: int) -> str:
    """Markdown: every algorithm and scene at the reference count, then means over counts."""
    head = "| algorithm | scene | superpixels | pureness | ICV | EV | UE | BR |\n" \
           "|---|---|---:|---:|---:|---:|---:|---:|\n"

    def line(alg: str, scene: str, r: dict[str, Any]) -> str:
        return (f"| {alg} | {scene} | {r['superpixels']:.0f} | {r['pureness']:.4f} | "
                f"{r['icv']:.5f} | {r['ev']:.4f} | {r['ue']:.4f} | {r['br']:.4f} |\n")

    ref = [r for r in rows if r["block"] == reference_block]
    text = f"### Block edge {reference_block} cells (the paper's rule of thumb)\n\n" + head
    for r in ref:
        text += line(r["algorithm"], r["scene"], r)
    for alg, m in _mean_over(ref, "superpixels").items():
        text += line(f"**{alg}**", "mean", m)
    blocks = sorted({int(r["block"]) for r in rows})
    text += f"\n### Mean over all scenes and block edges {blocks}\n\n" + head
    for alg, m in _mean_over(rows, "superpixels").items():
        text += line(alg, "all", m)
    return text


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)





def run_supercell_evaluation(
    out_dir: str | Path,
    *,
    scenes: int = 4,
    seed: int = 0,
    quick: bool = False,
    progress: bool = True,
    scene_factory: Callable[[int], Scene] | None = None,
    blocks: Sequence[int] | None = None,
    rooms: int = 4,
    intel: bool = True,
) -> EvaluationResult:
    """Run the evaluation of section IV and write its tables and figures into ``out_dir``.

    ``scene_factory(seed) -> Scene`` defaults to :func:`tabletop_scene` (the simulator);
    ``blocks`` (block edges, i.e. superpixel counts) defaults to ``8, 12, ..., 32``
    (``8, 16, 32`` with ``quick``, which also shrinks the parameter grids); ``rooms`` labelled
    room maps (:mod:`sogm_service.eval.roomeval`, 0: none) at 8- and 16-cell blocks; ``intel``:
    the Intel replay's table too.
    """
    t0 = time.time()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    make = scene_factory or tabletop_scene
    edges = tuple(blocks or (BLOCKS_QUICK if quick else BLOCKS_FULL))
    grids = parameter_grids(quick)
    total = scenes + sum(len(g) for g in grids.values()) * len(edges) + (10 if rooms else 0) \
        + intel
    bar = _Progress(total, progress)
    scene_list = []
    for k in range(scenes):
        scene_list.append(make(seed + k))
        bar.step(f"mapped {scene_list[-1].name}")
    rows: list[dict[str, Any]] = []
    chosen: dict[tuple[str, int], Params] = {}
    figure_block = REFERENCE_BLOCK if REFERENCE_BLOCK in edges else edges[0]
    shown: dict[str, Labels] = {}
    for alg in ALGORITHMS:
        for block in edges:
            params, labels = _tune(alg, block, scene_list, grids[alg], bar)
            chosen[(alg, block)] = params
            rows.extend(_rows_for(alg, block, params, labels, scene_list))
            if block == figure_block:
                shown[alg] = labels[-1]
    room_rows = run_room_evaluation(rooms, seed, step=bar.step,
                                    seeds_grid=SEEDS_QUICK if quick else SEEDS_GRID) \
        if rooms else []
    intel_table = intel_rows(intel_stack()) if intel else []
    if intel:
        bar.step("Intel replay")
    bar.close()
    files = [out / "results.csv", out / "results.md", out / "segmentations.png"]
    write_csv(files[0], rows)
    text = markdown_tables(rows, figure_block)
    if room_rows:
        files.append(out / "rooms.csv")
        write_rows(files[-1], room_rows)
        text += (f"\n### Room maps ({rooms}, one occupancy layer): SEVDS against tuned SEEDS at "
                 f"equal count\n\n" + rooms_markdown(room_rows))
    if intel_table:
        files.append(out / "intel.csv")
        write_rows(files[-1], intel_table)
        text += "\n### The Intel replay (5 cm, no labels)\n\n" + intel_markdown(intel_table)
    files[1].write_text(f"# SEVDS evaluation ({scenes} scenes, seed {seed})\n\n{text}")
    cv2.imwrite(str(files[2]), segmentation_figure(scene_list[-1], shown))
    files += metric_plots(rows, out)
    return EvaluationResult(out, rows, text, files, chosen, time.time() - t0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("eval-supercells"),
                   help="output folder (default %(default)s)")
    p.add_argument("--scenes", type=int, default=4, help="number of scenes (default 4)")
    p.add_argument("--rooms", type=int, default=4,
                   help="labelled room maps to compare SEVDS and SEEDS on (default 4, 0: none)")
    p.add_argument("--no-intel", dest="intel", action="store_false",
                   help="skip the Intel replay's table (its 910 scans are fused first)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first scene (default 0)")
    p.add_argument("--quick", action="store_true",
                   help="3 superpixel counts and minimal parameter grids")


def run_eval(args: argparse.Namespace) -> int:
    """Handler of ``eval supercells``: run, then print the markdown table and the files."""
    if args.scenes < 1 or args.rooms < 0:
        print("sogm-service: eval supercells: --scenes must be >= 1 and --rooms >= 0",
              file=sys.stderr)
        return 2
    result = run_supercell_evaluation(args.out, scenes=args.scenes, seed=args.seed,
                                      quick=args.quick, progress=True, rooms=args.rooms,
                                      intel=args.intel)
    print(result.markdown)
    print(f"wrote {len(result.files)} files to {result.out_dir} in {result.seconds:.0f} s")
    return 0
