"""Supercells -> topometric graph (paper section III-D.2, Fig. 6, Eq. 11).

:func:`extract_supercells` runs SEVDS (:mod:`~sogm_service.core.sevds.segment`, Eq. 7-10)
on an N-layer SOGM
window and turns the label image into the paper's triples ``C = (T_c, L_c, P_c)``:

* ``T_c`` -- the node's place in map coordinates: the centre of the supercell's cell nearest its
  centroid (the mean continuous cell coordinate ``(u, v)`` of its cells), mapped by
  ``GridGeometry.cell_to_world()`` (cell centres on integers).  The centroid of a bent or
  hollow supercell can lie outside it, on another object; the node never does (ties: the first
  such cell in raster order).  The centroid itself is kept next to it;
* ``L_c`` -- the adjacent supercells (sharing a 4-neighbour cell edge);
* ``P_c`` -- the feature vector of Eq. 11.  ``Odd(P_c)_n = prod_{m in c} Odd(P(m_n))`` is, in
  log-odds, the *sum* of the cells' log-odds of layer n (architecture, section 1:
  docs/architecture.md#1-log-odds-everywhere), reported in nats.
  The mean probability of every layer is reported next to it, because a sum of log-odds grows with
  the area and is hard to read on its own.

Each node's evidence (:func:`node_evidence`): *occupied* by its dominant layer when that layer's
mean probability exceeds ``0.5 + EVIDENCE_MARGIN``, *free* when no layer does but one lies below
``0.5 - EVIDENCE_MARGIN`` (observed free floor is evidence), *unknown* when every layer's mean is
within the margin of 0.5 (no cell observed, or as much for as against).

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

EVIDENCE_MARGIN = 0.01
"""How far from 0.5 a node's mean probability must lie to count as evidence."""
FREE = -1
""":func:`node_evidence` of a node observed free (no layer occupied)."""
UNKNOWN = -2
""":func:`node_evidence` of a node without evidence."""


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
    ``nodes_cell`` ``(S, 2)`` the u, v of each supercell's cell nearest its centroid and
    ``positions`` ``(S, 2)`` its map x, y (``T_c``: inside the supercell); ``areas`` ``(S,)``
    cells; ``edges`` ``(E, 2)`` pairs ``i < j``; ``logodds_sum`` and ``mean_probability``
    ``(S, N)`` (Eq. 11 in nats, and the mean of P per layer).
    """

    labels: npt.NDArray[np.int32]
    geometry: GridGeometry
    centroids: F64
    centroids_cell: F64
    areas: npt.NDArray[np.int64]
    edges: npt.NDArray[np.int32]
    logodds_sum: F64
    mean_probability: F64
    nodes_cell: npt.NDArray[np.int64]
    positions: F64

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

    def evidence(self) -> npt.NDArray[np.int64]:
        """:func:`node_evidence` of every node."""
        return node_evidence(self.mean_probability)

    def nodes(self) -> list[Supercell]:
        """The graph as a list of :class:`Supercell` (for the wire and for people)."""
        nbrs = self.neighbors()
        res2 = self.geometry.resolution**2
        return [
            Supercell(i, float(self.positions[i, 0]), float(self.positions[i, 1]),
                      int(self.areas[i]), float(self.areas[i] * res2), nbrs[i],
                      tuple(float(x) for x in self.logodds_sum[i]),
                      tuple(float(x) for x in self.mean_probability[i]))
            for i in range(self.count)
        ]


def node_evidence(mean_probability: npt.ArrayLike,
                  margin: float = EVIDENCE_MARGIN) -> npt.NDArray[np.int64]:
    """``(S,)`` per node: its dominant layer (``>= 0``) when that layer's mean probability
    exceeds ``0.5 + margin``, else :data:`FREE` when a layer's lies below ``0.5 - margin``, else
    :data:`UNKNOWN`.  ``mean_probability``: ``(S, N)``."""
    mp = np.asarray(mean_probability, dtype=np.float64)
    if mp.ndim != 2 or mp.shape[1] < 1:
        raise ValueError(f"expected (S, N) mean probabilities, got shape {mp.shape}")
    if mp.shape[0] == 0:
        return np.zeros(0, np.int64)
    best = np.argmax(mp, axis=1)
    out = np.where(np.min(mp, axis=1) < 0.5 - margin, FREE, UNKNOWN)
    return np.asarray(np.where(mp[np.arange(mp.shape[0]), best] > 0.5 + margin, best, out),
                      dtype=np.int64)


def nearest_cells(labels: npt.ArrayLike, centroids_cell: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """``(S, 2)`` u, v of each label's cell nearest its point in ``centroids_cell`` (``(S, 2)``
    continuous u, v; cell centres on integers; every label 0..S-1 used); ties go to the first
    cell in raster order."""
    lab = np.asarray(labels, dtype=np.int64)
    c = np.asarray(centroids_cell, dtype=np.float64)
    flat = lab.ravel()
    v, u = np.divmod(np.arange(flat.size, dtype=np.int64), lab.shape[1])
    d2 = (u - c[flat, 0]) ** 2 + (v - c[flat, 1]) ** 2
    dmin = np.full(c.shape[0], np.inf)
    np.minimum.at(dmin, flat, d2)
    near = np.flatnonzero(d2 <= dmin[flat])  # each label's nearest cells, in raster order
    _, first = np.unique(flat[near], return_index=True)  # (a sort of those few, not of all)
    return np.stack([u[near[first]], v[near[first]]], axis=1)


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
    inside = nearest_cells(lab, uv) if count else np.zeros((0, 2), np.int64)
    pos = inside.astype(np.float64) @ m[:2, :2].T + m[:2, 2]

    def per_layer(values: F64) -> F64:
        return np.stack([np.bincount(flat, layer.ravel(), count) for layer in values], axis=1)

    return SupercellGraph(lab, geo, xy, uv, areas.astype(np.int64), adjacency(lab),
                          per_layer(nats), per_layer(prob) / areas[:, None], inside, pos)


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
