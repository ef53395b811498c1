"""The client's ISMs are stamped now unless told otherwise (Unix time in seconds)."""

from __future__ import annotations

import time

import numpy as np

from sogm_service.client.isms import build_ism


def test_build_ism_stamps_now_by_default_and_keeps_a_given_stamp() -> None:
    cells = np.zeros((3, 4), np.int8)
    before = time.time()
    msg = build_ism(cells, resolution=0.1)
    assert before <= msg.stamp <= time.time()
    assert build_ism(cells, resolution=0.1, stamp=0.0).stamp == 0.0
    assert build_ism(cells, resolution=0.1, stamp=1.5e9).stamp == 1.5e9
