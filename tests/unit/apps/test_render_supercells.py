"""The supercell graph picture colours each node by its evidence (free floor is evidence)."""

from __future__ import annotations

import numpy as np

from sogm_service.apps.render import FREE_NODE_BGR, supercell_overlay
from sogm_service.core.sevds.segment import SevdsParams
from sogm_service.core.sevds.supercells import extract_supercells


def test_free_floor_nodes_are_orange_unknown_grey_occupied_in_their_layer_colour() -> None:
    p = np.full((1, 48, 48), 0.5, np.float32)
    p[0, :, 16:32] = 0.05  # observed free floor
    p[0, :, 32:] = 0.95  # occupied
    g, _ = extract_supercells(p, params=SevdsParams(block_size=16))
    ev = g.evidence()
    scale = 4
    img = supercell_overlay(p[0], g.labels, g.nodes_cell.astype(float),
                            [tuple(e) for e in g.edges.tolist()], ev, 1, scale)
    seen = set()
    for k, (u, v) in enumerate(g.nodes_cell):
        row = img.shape[0] - 1 - int((v + 0.5) * scale)  # the picture has map y up
        colour = tuple(int(c) for c in img[row, int((u + 0.5) * scale)])
        col = p[0, v, u]
        want = FREE_NODE_BGR if col < 0.1 else ((128, 128, 128) if col == 0.5 else None)
        if want is not None:
            assert colour == want, (k, col, colour)
        else:
            assert colour not in (FREE_NODE_BGR, (128, 128, 128))
        seen.add(round(float(col), 2))
    assert seen == {0.05, 0.5, 0.95}
