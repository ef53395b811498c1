"""The scan-matching stage of the server: per-source policy, stats and reports (service layer).

For each ISM key expression whose ``[ism.matching] mode`` is not ``off``, every ISM is matched
against the map around its claimed pose (:func:`sogm_service.core.matching.alignment.align`, paper
section III-C.2) before it is fused:

* ``correct``: an accepted match moves the ISM to the corrected pose before fusion; a failed
  one is fused as claimed (``on_failure = "fuse"``) or rejected (``"reject"``, counted as
  ``match_<reason>``).
* ``report``: the ISM is always fused as claimed; the correction is only published.

Either way the outcome goes out as a :class:`~sogm_service.wire.messages.MatchReport` on
``<prefix>/<map>/matching/<key>`` so a localisation stack can use it.  While the map has too
little around an ISM (the first ISMs of a layer) matching is skipped and the ISM fused.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh

from sogm_service.core.geometry import GridGeometry, wrap_angle
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.matching.alignment import Alignment, align, at_map_resolution
from sogm_service.core.matching.match import match_window
from sogm_service.core.matching.params import MatchParams
from sogm_service.service.config import MatchingSettings, ServiceConfig
from sogm_service.service.server.stats import Stats
from sogm_service.wire import codec, encodings
from sogm_service.wire.errors import IsmRejectedError
from sogm_service.wire.messages import IsmMessage, MatchReport, PoseModel


def match_params(settings: MatchingSettings, resolution: float) -> MatchParams:
    """The matcher's parameters (cells, radians) from a source's settings (metres, degrees)."""
    return MatchParams(
        model="homography" if settings.model == "homography" else "partial_affine",
        min_inliers=settings.min_inliers,
        max_translation=settings.max_translation_m / resolution,
        max_rotation=math.radians(settings.max_rotation_deg),
        window_extra=settings.margin_m / resolution)


class Matcher:
    """Applies one server's scan-matching policy; thread-safe stats."""

    def __init__(self, config: ServiceConfig, stats: Stats) -> None:
        self.config = config
        self.stats = stats
        self._lock = threading.Lock()
        self._sum_shift_m = 0.0
        self._sum_rot_deg = 0.0
        self._accepted = 0
        self._seconds = 0.0
        self._session: zenoh.Session | None = None
        res = config.map.resolution
        self._params = [match_params(s.matching, res) for s in config.ism]

    def enabled(self, source: int) -> bool:
        return self.config.ism[source].matching.mode != "off"

    def attach(self, session: zenoh.Session) -> None:
        """Reports go out on this session (``<prefix>/<map>/matching/<ISM key>``)."""
        self._session = session

    def place(self, tiled: TiledMap, msg: IsmMessage, key: str, layer: str, source: int,
              inc: npt.NDArray[np.int16], geometry: GridGeometry
              ) -> tuple[npt.NDArray[np.int16], GridGeometry]:
        """The increments and geometry to fuse; raises ``IsmRejectedError`` per policy."""
        settings = self.config.ism[source].matching
        params = self._params[source]
        started = time.perf_counter()
        ism, claimed = at_map_resolution(inc, geometry, self.config.map.resolution)
        window = match_window(claimed, params)
        alignment = align(ism, claimed, self._surroundings(tiled, settings.layer or layer,
                                                           window), window, params)
        elapsed = time.perf_counter() - started
        result = alignment.result
        if result is None:
            self.stats.count("match_skipped_empty_map")
            return inc, geometry
        self._account(result.accepted, result.reason, alignment, elapsed)
        self._report(msg, key, layer, settings.mode, alignment, elapsed)
        if settings.mode == "correct" and alignment.corrected is not None:
            return alignment.increments, alignment.corrected
        if settings.mode == "correct" and settings.on_failure == "reject":
            raise IsmRejectedError(f"match_{result.reason}",
                                   f"scan matching failed: {result.reason}")
        return inc, geometry

    @staticmethod
    def _surroundings(tiled: TiledMap, layer: str,
                      window: GridGeometry) -> npt.NDArray[np.int16] | None:
        """The map's ``layer`` in ``window``; None while the map has no such layer."""
        if layer not in tiled.layers:
            return None
        return tiled.sample(window, [layer], "biodds")[0]

    def _account(self, accepted: bool, reason: str, alignment: Alignment,
                 elapsed: float) -> None:
        self.stats.count("match_attempts")
        self.stats.count("match_accepted" if accepted else f"match_refused_{reason}")
        with self._lock:
            self._seconds += elapsed
            if accepted and alignment.corrected is not None:
                shift, rot = _shift(alignment.claimed, alignment.corrected)
                self._accepted += 1
                self._sum_shift_m += shift
                self._sum_rot_deg += math.degrees(abs(rot))

    def _report(self, msg: IsmMessage, key: str, layer: str, mode: str,
                alignment: Alignment, elapsed: float) -> None:
        if self._session is None or alignment.result is None:
            return
        r, claimed, corrected = alignment.result, alignment.claimed, alignment.corrected
        dx = dy = dyaw = None
        if corrected is not None:
            dx, dy = corrected.origin.x - claimed.origin.x, corrected.origin.y - claimed.origin.y
            dyaw = wrap_angle(corrected.origin.yaw - claimed.origin.yaw)
        report = MatchReport(
            map=self.config.map.name, key=key, layer=layer, robot=msg.robot, stamp=msg.stamp,
            mode=mode, accepted=r.accepted, reason=str(r.reason),
            claimed=_pose(claimed), corrected=None if corrected is None else _pose(corrected),
            dx_m=dx, dy_m=dy, dyaw_rad=dyaw, inliers=int(r.inliers),
            score_before=_finite(r.score_before), score_after=_finite(r.score_after),
            elapsed_ms=elapsed * 1e3)
        self._session.put(self.config.keys.matching(key), codec.encode(report),
                          encoding=zenoh.Encoding(encodings.MSGPACK))

    def stats_extra(self) -> dict[str, Any]:
        with self._lock:
            n = self._accepted
            return {"match_mean_shift_m": round(self._sum_shift_m / n, 4) if n else None,
                    "match_mean_rotation_deg": round(self._sum_rot_deg / n, 3) if n else None,
                    "match_seconds_total": round(self._seconds, 3)}


def _shift(a: GridGeometry, b: GridGeometry) -> tuple[float, float]:
    """How far the ISM centre moved (m) and how much it turned (rad) from ``a`` to ``b``."""
    (xa, ya), (xb, yb) = a.centre(), b.centre()
    return math.hypot(xb - xa, yb - ya), wrap_angle(b.origin.yaw - a.origin.yaw)


def _pose(g: GridGeometry) -> PoseModel:
    return PoseModel(x=g.origin.x, y=g.origin.y, yaw=g.origin.yaw)


def _finite(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None

