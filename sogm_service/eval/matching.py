"""Scan matching at a measured operating point: acceptance against wrong corrections.

``sogm-service eval matching [LOG] [--seed 0,1,2,3] [--min-inliers 6,8,10,12,16] ...``
runs :func:`evaluate` on a CARMEN log (default: the Intel Research Lab log) and prints the
trade-off table of :func:`trade_off` (markdown), optionally writing every trial as CSV.

Protocol (what a robot with a drifting pose estimate sends to the server):

1. The log's scans are fused in order at their **corrected** poses into a :class:`TiledMap`
   (the server's Eq. 1 path: laser ISM, ``prob_f32`` increments, ``TiledMap.fuse`` with
   biodds), so the map of the earlier scans is as good as the log allows.
2. Before scan ``i`` (``i >= start``, every ``stride``-th) is fused, its ISM is built at a
   **perturbed** pose: uniform +-``max_shift_m`` in x and y and +-``max_turn_deg`` in heading
   (``numpy.random.default_rng(seed)``) and matched against the map around that claimed pose,
   exactly as the server's matcher stage does it (``match_window``, ``TiledMap.sample`` with
   biodds, ``match_ism`` with the claimed pose as prior, ``corrected_geometry``).
3. Each trial records the raw matcher output with *permissive* acceptance settings
   (``min_inliers = 4``, no score gates), so every acceptance rule over ``min_inliers``,
   ``min_score`` and ``min_gain`` is evaluated afterwards from the same trials
   (:meth:`Trial.accepted_by`): the matcher's steps before acceptance do not depend on them.
   ``tests/unit/eval/test_matching.py`` checks this against ``match_ism`` run with each gate.
4. An accepted correction is **grossly wrong** when the corrected sensor pose is more than
   0.3 m or 5 deg from the log's corrected pose (the size of the perturbation itself).  A refused
   match keeps the claimed pose (the server fuses it as claimed, ``on_failure = "fuse"``).

Parameters that change the matching itself (Lowe's ratio, the window margin) need one pass each
(``--ratio 1.0,0.9``); the map is built once and shared by the passes.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from sogm_service.adapters.carmen import LaserScan, read_carmen
from sogm_service.adapters.laser import laser_ism
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.matching.match import (
    corrected_geometry,
    match_ism,
    match_window,
    prior_matrix,
)
from sogm_service.core.matching.params import MatchParams, MatchReason
from sogm_service.data import INTEL_LOG

LAYER = "obstacle"
MIN_KNOWN_CELLS = 200  # as the server's matcher: below this the map is too empty to match
GROSS_M = 0.3
GROSS_DEG = 5.0

# Outcomes whose transform passed the structural checks (inliers >= 4, not degenerate, within
# the correction bounds) and whose verdict depends only on the score gates.
_SCORED = {MatchReason.OK, MatchReason.POOR_AGREEMENT, MatchReason.NO_IMPROVEMENT}


@dataclass(frozen=True)
class Gate:
    """The acceptance settings evaluated afterwards (the rest of :class:`MatchParams` fixed);
    the defaults are :class:`MatchParams`'s."""

    min_inliers: int = MatchParams().min_inliers
    min_score: float = MatchParams().min_score
    min_gain: float = MatchParams().min_gain

    def label(self) -> str:
        return f"min_inliers={self.min_inliers} min_score={self.min_score:g} " \
               f"min_gain={self.min_gain:g}"


@dataclass(frozen=True)
class Trial:
    """One perturbed scan matched against the map of the earlier scans."""

    index: int
    variant: str
    reason: str  # with the permissive gate
    inliers: int
    n_matches: int
    score_before: float
    score_after: float
    error_before: tuple[float, float]  # (m, deg) claimed pose vs the log's corrected pose
    error_found: tuple[float, float] | None  # the same for the matcher's transform, if any

    def accepted_by(self, gate: Gate) -> bool:
        """Whether ``match_ism`` with ``gate``'s settings would accept this match."""
        if MatchReason(self.reason) not in _SCORED or self.inliers < gate.min_inliers:
            return False
        if not self.score_after >= gate.min_score:  # NaN: never
            return False
        return math.isnan(self.score_before) or \
            self.score_after >= self.score_before + gate.min_gain

    def error_after(self, gate: Gate) -> tuple[float, float]:
        """The pose error after matching: the correction when accepted, else the claim."""
        if self.accepted_by(gate) and self.error_found is not None:
            return self.error_found
        return self.error_before

    def grossly_wrong(self, gate: Gate) -> bool:
        if not self.accepted_by(gate) or self.error_found is None:
            return False
        return self.error_found[0] > GROSS_M or self.error_found[1] > GROSS_DEG


@dataclass
class Summary:
    """One row of the trade-off table."""

    variant: str
    gate: Gate
    trials: int
    accepted: int
    gross: int
    before_m: float
    before_deg: float
    after_m: float
    after_deg: float
    accepted_m: float
    accepted_deg: float
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def accepted_pct(self) -> float:
        return 100.0 * self.accepted / self.trials if self.trials else 0.0

    @property
    def gross_pct(self) -> float:
        """Grossly wrong corrections as a share of the *accepted* ones."""
        return 100.0 * self.gross / self.accepted if self.accepted else 0.0


def pose_error(a: Pose2D, b: Pose2D) -> tuple[float, float]:
    """(position error in m, heading error in degrees)."""
    return (math.hypot(a.x - b.x, a.y - b.y),
            abs(math.degrees(math.remainder(a.yaw - b.yaw, 2 * math.pi))))


def permissive(params: MatchParams) -> MatchParams:
    """``params`` with the acceptance gates opened (the trials record what they would decide)."""
    return replace(params, min_inliers=4, min_score=-math.inf, min_gain=-math.inf)


def evaluate(scans: Sequence[LaserScan], variants: dict[str, MatchParams], *,
             start: int = 150, stride: int = 1, seed: int = 0, resolution: float = 0.05,
             usable_range: float = 8.0, max_shift_m: float = 0.3, max_turn_deg: float = 5.0,
             progress: bool = False, gated: bool = False) -> list[Trial]:
    """Run the protocol of the module docstring; one :class:`Trial` per scan and variant.

    ``gated``: match with the variants' own acceptance settings instead of the permissive
    ones (then ``Trial.reason`` is ``match_ism``'s verdict; the tests compare the two).
    """
    tiled = TiledMap("eval", "map", TileLattice(resolution, 256))
    rng = np.random.default_rng(seed)
    limit = np.array([max_shift_m, max_shift_m, math.radians(max_turn_deg)])
    trials: list[Trial] = []
    opened = {name: (p if gated else permissive(p)) for name, p in variants.items()}

    def ism(scan: LaserScan, pose: Pose2D) -> tuple[GridGeometry, np.ndarray]:
        g, p = laser_ism(scan.ranges, scan.angles, pose, resolution,
                         min(usable_range, scan.max_range), device_max_range=scan.max_range)
        return g, logodds.increments(p, logodds.Encoding.PROB_F32, tiled.eps0)

    for i, scan in enumerate(scans):
        if i >= start and (i - start) % stride == 0:
            d = rng.uniform(-1.0, 1.0, 3) * limit
            claimed = Pose2D(scan.pose.x + d[0], scan.pose.y + d[1], scan.pose.yaw + d[2])
            g, inc = ism(scan, claimed)
            for name, params in opened.items():
                t = _trial(tiled, i, name, scan.pose, claimed, g, inc, params)
                if t is not None:
                    trials.append(t)
            if progress and (i - start) % (50 * stride) == 0:
                print(f"  scan {i}/{len(scans)}: {len(trials)} trials", file=sys.stderr)
        g, inc = ism(scan, scan.pose)
        tiled.fuse(LAYER, inc, g, "biodds")
    return trials


def _trial(tiled: TiledMap, index: int, variant: str, truth: Pose2D, claimed: Pose2D,
           g: GridGeometry, inc: np.ndarray, params: MatchParams) -> Trial | None:
    """What the server's ``IngestPipeline.align`` (:mod:`sogm_service.service.server.pipeline`)
    does, with the core functions."""
    window = match_window(g, params)
    if LAYER not in tiled.layers:
        return None
    surroundings = tiled.sample(window, [LAYER], "biodds")[0]
    if np.count_nonzero(surroundings) < MIN_KNOWN_CELLS:
        return None
    res = match_ism(inc, surroundings, params, prior_matrix(g, window))
    found = None
    if res.matrix is not None and res.reason in _SCORED:
        # The sensor sits at a fixed place in its ISM grid: carry it along.
        to_sensor = g.origin.inverse().compose(claimed)
        found = pose_error(corrected_geometry(g, window, res).origin.compose(to_sensor), truth)
    return Trial(index, variant, res.reason.value, res.inliers, res.n_matches,
                 res.score_before, res.score_after, pose_error(claimed, truth), found)


def summarize(trials: Iterable[Trial], variant: str, gate: Gate) -> Summary:
    ts = [t for t in trials if t.variant == variant]
    acc = [t for t in ts if t.accepted_by(gate)]
    b = np.array([t.error_before for t in ts]).reshape(-1, 2)
    a = np.array([t.error_after(gate) for t in ts]).reshape(-1, 2)
    fa = np.array([t.error_found for t in acc]).reshape(-1, 2)

    def mean(x: np.ndarray) -> float:
        return float(x.mean()) if x.size else math.nan

    return Summary(variant, gate, len(ts), len(acc), sum(t.grossly_wrong(gate) for t in ts),
                   mean(b[:, 0]), mean(b[:, 1]), mean(a[:, 0]), mean(a[:, 1]),
                   mean(fa[:, 0]), mean(fa[:, 1]))


def trade_off(trials: Sequence[Trial], gates: Sequence[Gate]) -> list[Summary]:
    variants = list(dict.fromkeys(t.variant for t in trials))
    return [summarize(trials, v, g) for v in variants for g in gates]


def markdown(rows: Sequence[Summary]) -> str:
    head = ("| variant | min_inliers | min_score | min_gain | accepted | grossly wrong "
            "(of accepted) | mean error before | after (all) | after (accepted) |\n"
            "|---|---|---|---|---|---|---|---|---|\n")
    body = "".join(
        f"| {r.variant} | {r.gate.min_inliers} | {r.gate.min_score:g} | {r.gate.min_gain:g} "
        f"| {r.accepted}/{r.trials} = {r.accepted_pct:.1f} % | {r.gross} = {r.gross_pct:.2f} % "
        f"| {r.before_m:.3f} m / {r.before_deg:.2f}° | {r.after_m:.3f} m / {r.after_deg:.2f}° "
        f"| {r.accepted_m:.3f} m / {r.accepted_deg:.2f}° |\n" for r in rows)
    return head + body


def write_csv(trials: Sequence[Trial], path: Path) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["index", "variant", "reason", "inliers", "n_matches", "score_before",
                    "score_after", "before_m", "before_deg", "found_m", "found_deg"])
        for t in trials:
            fm, fd = t.error_found if t.error_found is not None else (math.nan, math.nan)
            w.writerow([t.index, t.variant, t.reason, t.inliers, t.n_matches,
                        f"{t.score_before:.5f}", f"{t.score_after:.5f}",
                        f"{t.error_before[0]:.4f}", f"{t.error_before[1]:.3f}",
                        f"{fm:.4f}", f"{fd:.3f}"])


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sogm-service eval matching",
                                description=__doc__.split("\n")[0] if __doc__ else None)
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of eval matching (the CLI adds them to its own subcommand)."""
    p.add_argument("log", nargs="?", type=Path, default=INTEL_LOG,
                   help="a CARMEN log, plain or gzip")
    p.add_argument("--limit", type=int, default=None, metavar="N",
                   help="read at most this many scans (default: all)")
    p.add_argument("--start", type=int, default=150, metavar="N",
                   help="index of the first scan matched (the scans before build the map)")
    p.add_argument("--stride", type=int, default=1, metavar="K",
                   help="match every k-th scan from --start")
    p.add_argument("--seed", type=_ints, default=[0], metavar="S,S",
                   help="perturbation seeds, e.g. 0,1,2,3: one pass each, pooled in the table")
    p.add_argument("--resolution", type=float, default=0.05, metavar="M",
                   help="map and ISM cell size (m)")
    p.add_argument("--usable-range", type=float, default=8.0, metavar="M",
                   help="ISM range (m)")
    p.add_argument("--min-inliers", type=_ints, default=[6, 8, 10, 12, 16], metavar="N,N",
                   help="acceptance thresholds on the inlier count (keypoints), one table "
                        "row each")
    p.add_argument("--min-score", type=_floats, default=[0.3], metavar="X,X",
                   help="acceptance thresholds on the match score (unitless)")
    p.add_argument("--min-gain", type=_floats, default=[0.0], metavar="X,X",
                   help="acceptance thresholds on the score gain over the prior pose (unitless)")
    p.add_argument("--ratio", type=_floats, default=[1.0], metavar="X,X",
                   help="Lowe's ratio values (one matching pass each)")
    p.add_argument("--margin-cells", type=_floats, default=[0.0], metavar="CELLS,CELLS",
                   help="extra window margin values in cells (one pass each)")
    p.add_argument("--csv", type=Path, default=None, metavar="FILE",
                   help="write every trial here (default: none)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def variants_of(ratios: Sequence[float], margins: Sequence[float],
                base: MatchParams | None = None) -> dict[str, MatchParams]:
    """One matching pass per (ratio, margin) combination, named for the table."""
    base = base or MatchParams()
    out = {}
    for r in ratios:
        for m in margins:
            params = replace(base, ratio=r)
            if m:
                params = replace(params, window_extra=m)
            out[f"ratio={r:g}" + (f" margin={m:g}" if m else "")] = params
    return out


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Evaluate as the parsed options say; the exit status."""
    if not args.log.exists():
        print(f"sogm-service: eval matching: no such file {args.log}", file=sys.stderr)
        return 2
    scans = list(read_carmen(args.log, limit=args.limit))
    if len(scans) <= args.start:
        print(f"sogm-service: eval matching: {len(scans)} scans, none after --start "
              f"{args.start}", file=sys.stderr)
        return 2
    variants = variants_of(args.ratio, args.margin_cells)
    trials = [t for seed in args.seed
              for t in evaluate(scans, variants, start=args.start, stride=args.stride,
                                seed=seed, resolution=args.resolution,
                                usable_range=args.usable_range, progress=not args.quiet)]
    gates = [Gate(k, s, g) for k in args.min_inliers for s in args.min_score
             for g in args.min_gain]
    print(markdown(trade_off(trials, gates)), end="")
    if args.csv is not None:
        write_csv(trials, args.csv)
        print(f"wrote {args.csv}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
