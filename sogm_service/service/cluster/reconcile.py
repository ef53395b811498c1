"""Reconciliation of a replica with its primary (:mod:`sogm_service.service.cluster.cluster`):
every quiet interval a replica compares each tile that changed and then stayed quiet with its
primary's copy (by content digest) and installs the primary's when they differ, replaying what
was journaled meanwhile.
"""

from __future__ import annotations

import logging

from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.service.cluster.exchange import Pulled, TileExchange
from sogm_service.service.cluster.handover import replay_plan

log = logging.getLogger(__name__)


class Reconciliation(TileExchange):
    """A replica's rounds of comparing its tiles with their primaries'."""

    # -- reconciliation with the primary (module docstring) ---------------------------------
    def _reconcile_round(self) -> None:
        view = self._view
        if view is None or self._busy or self.settings.replicas < 2 or len(view.members) < 2:
            return
        for tile in self.tiled.resident():
            index = tile.index
            if self._stop.is_set() or not self._events.empty():
                return  # a membership change first
            version, seen = tile.version, self._seen.get(index)
            self._seen[index] = version
            if version != seen or version == self._checked.get(index):
                continue  # still changing, or confirmed since its last change
            primary = view.primary(index)
            if primary is None or primary == self.me or not view.owns(self.me, index):
                continue
            try:
                self._reconcile(index, primary)
            except Exception:
                log.exception("cluster: reconciling tile %s failed", index)
        for index in list(self._seen):
            if index not in self.tiled.tiles:
                self._seen.pop(index, None)
                self._checked.pop(index, None)

    def _reconcile(self, index: TileIndex, primary: str) -> None:
        """Compare tile ``index`` with its primary's copy and adopt that when they differ."""
        with self._gate:
            self._reconciling.add(index)  # from now on its ISMs wait in the journal
        got: Pulled | None = None
        try:
            with self._flight:
                landed = self._flight.wait_for(lambda: not self._inflight.get(index),
                                               self.settings.handover_timeout_s)
            if not landed:
                self.stats.count("cluster_reconcile_deferred")
                return
            digest = self._local_digest(index)
            got = self._first(self._ask(index, digest, self.settings.handover_timeout_s),
                              only=primary)
            self.stats.count("cluster_reconcile_checked")
        finally:
            self._finish_reconcile(index, got)

    def _finish_reconcile(self, index: TileIndex, got: Pulled | None) -> None:
        """Install the primary's copy (if it differs) and fuse what was journaled meanwhile."""
        with self._gate:
            applied: dict[str, Mark] = {}
            if got is not None and got.status == "tile" and got.blob is not None and \
                    self._install(index, got.blob, got.applied):
                applied = got.applied
                self.stats.count("cluster_tiles_reconciled")
            keep, skip = replay_plan(self._journal.pop(index, []), applied)
            for job in keep:
                self.tiled.fuse(job.layer, job.increments, job.geometry, job.interp, job.stamp,
                                lambda i: i == index, (job.key, (job.stamp, job.digest)))
            if skip:
                self._skip[index] = skip
            self._reconciling.discard(index)
            current = self.tiled.tiles.get(index)
            if current is not None and got is not None and got.status in ("same", "tile"):
                self._checked[index] = self._seen[index] = current.version
