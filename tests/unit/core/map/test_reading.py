"""Reads of the tiled map touch only the layers asked for: a tile's other layers are never
read nor copied, whatever path (mosaic and warp, aligned slice, gathered taps) the window
takes."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap

RES = 0.05


class Untouchable(np.ndarray):  # type: ignore[type-arg]
    """A plane that fails the test when anything reads it."""

    def __getitem__(self, key: Any) -> Any:
        raise AssertionError("a layer the query did not ask for was read")

    def __array__(self, *args: Any, **kwargs: Any) -> Any:
        raise AssertionError("a layer the query did not ask for was copied")


def _map(other_layers: int) -> TiledMap:
    tiled = TiledMap("m", "map", TileLattice(RES, 64))
    inc = np.full((200, 200), 300, np.int16)
    for name in ["asked/a", "asked/b"]:
        tiled.fuse(name, inc, GridGeometry(RES, 200, 200, Pose2D(0.0, 0.0, 0.0)), "biodds", 0.0)
    for k in range(other_layers):  # each robot its own layers, in the same tiles
        tiled.fuse(f"robot{k}/x", inc, GridGeometry(RES, 200, 200, Pose2D(0.0, 0.0, 0.0)),
                   "biodds", 0.0)
    asked = {tiled.layer_id("asked/a"), tiled.layer_id("asked/b")}
    for tile in tiled.resident():
        for lid, plane in list(tile.planes.items()):
            if lid not in asked:
                tile.planes[lid] = plane.view(Untouchable)
    return tiled


WINDOWS = {
    "rotated (mosaic and warp)": GridGeometry(RES, 120, 100, Pose2D(1.0, 1.5, 0.5)),
    "aligned (a slice)": GridGeometry(RES, 120, 100, Pose2D(1.0, 1.5, 0.0)),
    "coarse (gathered taps)": GridGeometry(RES * 8, 20, 20, Pose2D(0.2, 0.3, 0.3)),
}


@pytest.mark.parametrize("name", list(WINDOWS))
def test_a_window_reads_only_the_layers_it_names(name: str) -> None:
    tiled = _map(other_layers=32)
    out: npt.NDArray[np.int16] = tiled.sample(WINDOWS[name], ["asked/a", "asked/b"])
    clean = _map(other_layers=0)
    np.testing.assert_array_equal(out, clean.sample(WINDOWS[name], ["asked/a", "asked/b"]))
    assert out.shape[0] == 2 and np.count_nonzero(out) > 0


def test_the_untouchable_plane_does_fail_when_read() -> None:
    tiled = _map(other_layers=1)
    with pytest.raises(AssertionError, match="did not ask"):
        tiled.sample(WINDOWS["rotated (mosaic and warp)"], ["robot0/x"])
