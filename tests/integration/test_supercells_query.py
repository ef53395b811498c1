"""The supercells queryable and its CLI over a real server (paper section III-D.2, Fig. 6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sogm_service.apps.cli import main as cli_main
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.sevds.supercells import FREE, UNKNOWN, node_evidence
from sogm_service.wire.errors import ServiceError
from tests.conftest import ServerProcess, wait_processed

pytestmark = pytest.mark.integration


def _two_regions(client: object) -> None:
    """Layer a: occupied (p=0.9) on the left half of a 6.4 m square; layer b: free there."""
    a = np.full((128, 128), 0.5, np.float32)
    a[:, :64] = 0.9
    b = np.full((128, 128), 0.5, np.float32)
    b[:, :64] = 0.1
    b[:, 64:] = 0.8
    client.publish_ism("ism/r/laser/a", a, resolution=0.05)  # type: ignore[attr-defined]
    client.publish_ism("ism/r/cam/b", b, resolution=0.05)  # type: ignore[attr-defined]


def test_supercell_graph_partitions_the_window_with_eq11_features(
        server: ServerProcess) -> None:
    with server.client(timeout=30) as client:
        _two_regions(client)
        wait_processed(client, 2)
        reply = client.supercells(x=3.2, y=3.2, width=6.4, height=6.4, labels=True)
    labels = reply.labels.array()
    assert labels.shape == (128, 128)
    nodes = reply.nodes
    assert sum(n.area_cells for n in nodes) == 128 * 128
    assert sorted(np.unique(labels)) == [n.id for n in nodes]
    for n in nodes:  # the adjacency is symmetric and real
        for m in n.neighbors:
            assert n.id in nodes[m].neighbors
    ids = {n.id for n in nodes}
    assert all(set(n.neighbors) <= ids for n in nodes)
    # No supercell straddles the boundary between the two regions (x = 3.2 m).
    for n in nodes:
        cols = np.nonzero(labels == n.id)[1]
        assert cols.max() < 64 or cols.min() >= 64
    # Eq. 11: a supercell on the left holds layer a's log-odds times its area.
    left = next(n for n in nodes if n.x < 3.0)
    inc_a = logodds.increments(np.array([0.9], np.float32), "prob_f32")[0] / logodds.SCALE
    assert left.logodds_sum[0] == pytest.approx(inc_a * left.area_cells, rel=1e-2)
    assert left.mean_probability[0] == pytest.approx(0.9, abs=0.01)
    assert left.mean_probability[1] == pytest.approx(0.1, abs=0.01)
    assert left.area_m2 == pytest.approx(left.area_cells * 0.05 ** 2)
    assert 0.0 <= left.x <= 3.2 and 0.0 <= left.y <= 6.4


def test_nodes_sit_inside_their_supercells_and_free_floor_is_evidence(
        server: ServerProcess) -> None:
    # A one-cell wall ring around free floor, unknown outside (as a room of a laser map).
    p = np.full((128, 128), 0.5, np.float32)
    p[16:112, 16:112] = 0.95
    p[17:111, 17:111] = 0.05
    with server.client(timeout=30) as client:
        client.publish_ism("ism/r/laser/occ", p, resolution=0.05)
        wait_processed(client, 1)
        reply = client.supercells(x=3.2, y=3.2, width=6.4, height=6.4, labels=True)
    labels = reply.labels.array()
    g = GridGeometry(reply.resolution, reply.width, reply.height,
                     Pose2D(reply.origin.x, reply.origin.y, reply.origin.yaw))
    uv = (g.world_to_cell() @ np.array([[n.x, n.y, 1.0] for n in reply.nodes]).T)[:2].T
    u, v = np.rint(uv).astype(int).T
    assert (labels[v, u] == [n.id for n in reply.nodes]).all()  # every node in its own cell
    evidence = node_evidence(np.array([n.mean_probability for n in reply.nodes]))
    cells = np.bincount(labels.ravel(), minlength=len(reply.nodes))

    def only(mask: np.ndarray) -> np.ndarray:  # supercells wholly of these cells
        return np.bincount(labels[mask], minlength=len(reply.nodes)) == cells

    floor, outside = only(p < 0.1), only(p == 0.5)
    assert floor.sum() >= 50 and (evidence[floor] == FREE).all()
    assert outside.sum() >= 10 and (evidence[outside] == UNKNOWN).all()
    for k in range(len(reply.nodes)):  # compact: no supercell spans more than 4 blocks
        rows, cols = np.nonzero(labels == k)
        assert max(np.ptp(rows), np.ptp(cols)) + 1 <= 4 * 8


def test_supercell_query_with_bad_parameters_names_them(server: ServerProcess) -> None:
    with server.client(timeout=30) as client:
        _two_regions(client)
        wait_processed(client, 2)
        with pytest.raises(ServiceError) as err:
            client.supercells(x=3.2, y=3.2, width=6.4, height=6.4, bins=1)
        assert err.value.parameter == "bins"
        with pytest.raises(ServiceError) as err:
            client.supercells(x=3.2, y=3.2, width=0.2, height=0.2)
        assert err.value.parameter == "block_size"


def test_query_supercells_cli_writes_the_graph_picture(server: ServerProcess,
                                                        tmp_path: Path) -> None:
    with server.client() as client:
        _two_regions(client)
        wait_processed(client, 2)
    png = tmp_path / "graph.png"
    code = cli_main(["query", "supercells", "--connect", server.endpoint, "--x", "3.2",
                     "--y", "3.2", "--width", "6.4", "--height", "6.4", "--timeout", "30",
                     "--png", str(png)])
    assert code == 0
    assert png.stat().st_size > 1000
