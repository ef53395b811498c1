"""The evaluation's figures (eval/figures): plots drawn with every series and its legend."""

from __future__ import annotations

import numpy as np

from sogm_service.eval import figures


def test_line_plot_draws_series_and_legend() -> None:
    img = figures.line_plot({"a": ([1, 2, 3], [0.1, 0.5, 0.2]), "b": ([1, 3], [0.3, 0.3])},
                            "title", "x", "y", size=(400, 300))
    assert img.shape == (300, 400, 3)
    for colour in figures.COLOURS[:2]:
        assert np.any(np.all(img == colour, axis=2)), f"series colour {colour} not drawn"
