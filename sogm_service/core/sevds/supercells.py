"""Supercells -> topometric graph (paper section III-D.2, Fig. 6, Eq. 11).

:func:`extract_supercells` runs SEVDS (:mod:`~sogm_service.core.sevds.segment`, Eq. 7-10)
on an N-layer SOGM
window and turns the label image into the paper's triples ``C = (T_c, L_c, P_c)``:

* ``T_c`` -- the centroid in map coordinates: the mean continuous cell coordinate ``(u, v)`` of the
  supercell's cells, mapped by ``GridGeometry.cell_to_world()`` (cell centres on integers);
* ``L_c`` -- the adjacent supercells (sharing a 4-neighbour cell edge);
* ``P_c`` -- the feature vector of Eq. 11.  ``Odd(P_c)_n = prod_{m in c} Odd(P(m_n))`` is, in
  log-odds, the *sum* of the cells' log-odds of layer n (architecture, section 1:
  docs/architecture.md#1-log-odds-everywhere), reported in nats.
  The mean probability of every layer is reported next to it, because a sum of log-odds grows with
  the area and is hard to read on its own.

The input is either a float stack of probabilities in [0, 1] or the map's own int16 fixed-point
log-odds (:mod:`sogm_service.core.logodds`); in the second case the log-odds sums are exact.  For a
probability stack the log-odds are taken after the map's clamp ``[eps0, 1 - eps0]``, so a cell of
probability 0 or 1 adds a finite amount, as it would inside the map.  Pure numpy, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry
from sogm_service.core.sevds.segment import SevdsParams, SevdsResult, sevds

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Supercell:
    """One node of the topometric graph: the paper's triple (T_c, L_c, P_c)."""

    id: int
    x: float
    y: float
    area_cells: int
    area_m2: float
    neighbors: tuple[int, ...]
    logodds_sum: tuple[float, ...]
    mean_probability: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class SupercellGraph:
    """Supercells of one window: label image, per-node arrays and the adjacency.

    ``centroids`` ``(S, 2)`` map x, y; ``centroids_cell`` ``(S, 2)`` continuous u, v;
    ``areas`` ``(S,)`` cells; ``edges`` ``(E, 2)`` pairs ``i < j``; ``logodds_sum`` and
    ``mean_probability`` ``(S, N)`` (Eq. 11 in nats, and the mean of P per layer).
    """

    labels: npt.NDArray[np.int32]
    geometry: GridGeometry
    centroids: F64
    centroids_cell: F64
    areas: npt.NDArray[np.int64]
    edges: npt.NDArray[np.int32]
    logodds_sum: F64
    mean_probability: F64

    @property
    def count(self) -> int:
        return int(self.areas.size)

    @property
    def areas_m2(self) -> F64:
        return np.asarray(self.areas * self.geometry.resolution**2, dtype=np.float64)

    def neighbors(self) -> list[tuple[int, ...]]:
        """``L_c`` of every supercell, ascending ids."""
        out: list[list[int]] = [[] for _ in range(self.count)]
        for a, b in self.edges.tolist():
            out[a].append(b)
            out[b].append(a)
        return [tuple(sorted(n)) for n in out]

    def nodes(self) -> list[Supercell]:
        """The graph as a list of :class:`Supercell` (for the wire and for people)."""
        nbrs = self.neighbors()
        res2 = self.geometry.resolution**2
        return [
            Supercell(i, float(self.centroids[i, 0]), float(self.centroids[i, 1]),
                      int(self.areas[i]), float(self.areas[i] * res2), nbrs[i],
                      tuple(float(x) for x in self.logodds_sum[i]),
                      tuple(float(x) for x in self.mean_probability[i]))
            for i in range(self.count)
        ]


def split_stack(stack: npt.ArrayLike, eps0: float = logodds.DEFAULT_EPS0) -> tuple[F64, F64]:
    """``(probabilities, log-odds in nats)`` of a probability or int16 fixed log-odds stack."""
    arr = np.asarray(stack)
    if arr.dtype == logodds.DTYPE:
        nats = arr.astype(np.float64) / logodds.SCALE
        return np.asarray(logodds.sigmoid(nats), dtype=np.float64), nats
    p = arr.astype(np.float64)
    if p.size and (np.nanmin(p) < 0.0 or np.nanmax(p) > 1.0):
        raise ValueError("a float stack must hold probabilities in [0, 1]")
    eps0 = logodds.check_eps0(eps0)
    return p, np.asarray(logodds.logit(np.clip(p, eps0, 1.0 - eps0)), dtype=np.float64)


def adjacency(labels: npt.ArrayLike) -> npt.NDArray[np.int32]:
    """``(E, 2)`` sorted unique pairs ``i < j`` of labels that share a 4-neighbour edge."""
    lab = np.asarray(labels, dtype=np.int64)
    pairs = [np.stack([lab[:, :-1].ravel(), lab[:, 1:].ravel()], axis=1),
             np.stack([lab[:-1, :].ravel(), lab[1:, :].ravel()], axis=1)]
    both = np.concatenate(pairs)
    both = np.sort(both[both[:, 0] != both[:, 1]], axis=1)
    return np.unique(both, axis=0).astype(np.int32).reshape(-1, 2)


def supercell_graph(labels: npt.ArrayLike, stack: npt.ArrayLike,
                    geometry: GridGeometry | None = None,
                    eps0: float = logodds.DEFAULT_EPS0) -> SupercellGraph:
    """Centroids, areas, adjacency and Eq. 11 features of a label image over a stack.

    ``labels`` must hold ``0..S-1`` (every id used); ``geometry`` defaults to a unit grid at the
    origin (centroids then in cell units).
    """
    lab = np.ascontiguousarray(labels, dtype=np.int32)
    prob, nats = split_stack(stack, eps0)
    if prob.ndim != 3 or prob.shape[1:] != lab.shape:
        raise ValueError(f"stack {prob.shape} does not match labels {lab.shape}")
    geo = geometry or GridGeometry(1.0, lab.shape[1], lab.shape[0])
    if geo.shape != lab.shape:
        raise ValueError(f"geometry {geo.shape} does not match labels {lab.shape}")
    flat = lab.ravel()
    count = int(flat.max()) + 1 if flat.size else 0
    areas = np.bincount(flat, minlength=count)
    if flat.size and (flat.min() < 0 or np.any(areas == 0)):
        raise ValueError("labels must be 0..S-1 with every id used")
    v, u = np.indices(lab.shape)
    uv = np.stack([np.bincount(flat, u.ravel(), count), np.bincount(flat, v.ravel(), count)],
                  axis=1) / areas[:, None]
    m = geo.cell_to_world()
    xy = uv @ m[:2, :2].T + m[:2, 2]

    def per_layer(values: F64) -> F64:
        return np.stack([np.bincount(flat, layer.ravel(), count) for layer in values], axis=1)

    return SupercellGraph(lab, geo, xy, uv, areas.astype(np.int64), adjacency(lab),
                          per_layer(nats), per_layer(prob) / areas[:, None])


def extract_supercells(stack: npt.ArrayLike, geometry: GridGeometry | None = None,
                       params: SevdsParams | None = None,
                       eps0: float = logodds.DEFAULT_EPS0) -> tuple[SupercellGraph, SevdsResult]:
    """SEVDS (Eq. 7-10) on an ``(N, H, W)`` window, then its graph (Fig. 6, Eq. 11).

    ``stack``: float probabilities or int16 fixed log-odds.  Returns the graph and the raw SEVDS
    result (labels, per-layer histograms).
    """
    prob, _ = split_stack(stack, eps0)
    result = sevds(prob, params)
    return supercell_graph(result.labels, stack, geometry, eps0), result
