"""CPU caps for the bench: one cgroup per process with the same CPU quota, as if each ran on a
host of its own (``cpu.max`` of cgroup v2, or ``cpu.cfs_quota_us`` of the v1 ``cpu``
controller), and the CPU time each group used (v2 ``cpu.stat``, v1 a twin group under
``cpuacct``).  Used by the ``cluster_scale`` row (:mod:`sogm_service.bench.cluster_scale`).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

PERIOD_US = 10_000
"""The quota's period: short, so a member's throttled stretches (at most 6 ms of 10) stay
within what its ingestion queue absorbs; with 100 ms the members' stalls, out of phase, held
the one publisher (BLOCK) and so every other member too."""
WEIGHT = 10
"""A bench group's CPU weight against a process outside them: the cap is a share the member
gets, not only a ceiling, while other work runs on the machine."""


class CpuCaps:
    """One cgroup per member under ``sogm-bench-<pid>``, each with the same CPU quota; removed
    by :meth:`close` (its processes moved back to the parent first, should any remain)."""

    def __init__(self, cap: float) -> None:
        self.cap = cap
        self.kind, self.root = _controller()
        self.base = self.root / f"sogm-bench-{os.getpid()}" if self.root else None
        self.made: list[Path] = []
        # v1 keeps CPU time in the cpuacct hierarchy: a twin group per member there
        acct = Path("/sys/fs/cgroup/cpuacct")
        self.acct = acct / self.base.name if self.kind == "v1" and self.base is not None \
            and os.access(acct, os.W_OK) else None
        if self.acct is not None:
            self.acct.mkdir()
        if self.base is not None:
            self.base.mkdir()
            self.made.append(self.base)
            if self.kind == "v2":  # the members' groups need the cpu controller below base
                (self.base / "cgroup.subtree_control").write_text("+cpu")

    @property
    def available(self) -> bool:
        return self.base is not None

    def describe(self) -> str:
        if not self.available:
            return "uncapped (no cgroup CPU controller here)"
        what = "cpu.max" if self.kind == "v2" else "cpu.cfs_quota_us"
        return (f"{self.cap:g} CPU per member (cgroup {self.kind} {what}, weight {WEIGHT}x a "
                "process)")

    def place(self, name: str, pid: int, capped: bool = True) -> None:
        """Put process ``pid`` (all its threads) in group ``name``, made with the quota (or,
        ``capped`` False, without).  Every group weighs ``WEIGHT`` times a plain process, so
        that on a machine busy with other work a member still gets its whole cap."""
        if self.base is None:
            return
        group = self.base / name
        if group not in self.made:
            group.mkdir()
            self.made.append(group)
            quota = int(self.cap * PERIOD_US)
            if self.kind == "v2":
                (group / "cpu.weight").write_text(str(100 * WEIGHT))
                if capped:
                    (group / "cpu.max").write_text(f"{quota} {PERIOD_US}")
            else:
                (group / "cpu.shares").write_text(str(1024 * WEIGHT))
                if capped:
                    (group / "cpu.cfs_period_us").write_text(str(PERIOD_US))
                    (group / "cpu.cfs_quota_us").write_text(str(quota))
        (group / "cgroup.procs").write_text(str(pid))
        if self.acct is not None:
            twin = self.acct / name
            if twin not in self.made:
                twin.mkdir()
                self.made.append(twin)
            (twin / "cgroup.procs").write_text(str(pid))

    def usage_s(self, name: str) -> float | None:
        """CPU seconds group ``name`` has used, every thread that ever ran in it included
        (None without a cgroup)."""
        if self.kind == "v2" and self.base is not None:
            for line in (self.base / name / "cpu.stat").read_text().splitlines():
                if line.startswith("usage_usec "):
                    return int(line.split()[1]) / 1e6
        if self.acct is not None:
            return int((self.acct / name / "cpuacct.usage").read_text()) / 1e9
        return None

    def close(self) -> None:
        for group in reversed(self.made):
            top = self.root if self.acct is None or not group.is_relative_to(self.acct) \
                else self.acct.parent
            try:
                for pid in (group / "cgroup.procs").read_text().split():
                    (top / "cgroup.procs").write_text(pid)  # type: ignore[operator]
                group.rmdir()
            except OSError:
                pass
        self.made.clear()
        if self.acct is not None:
            with suppress(OSError):
                self.acct.rmdir()


def _controller() -> tuple[str, Path | None]:
    """Where this machine's cgroup CPU controller is mounted: v2, else v1's ``cpu``."""
    v2 = Path("/sys/fs/cgroup")
    try:
        if "cpu" in (v2 / "cgroup.controllers").read_text().split() \
                and os.access(v2, os.W_OK):
            if "cpu" not in (v2 / "cgroup.subtree_control").read_text().split():
                (v2 / "cgroup.subtree_control").write_text("+cpu")
            return "v2", v2
    except OSError:
        pass
    v1 = Path("/sys/fs/cgroup/cpu")
    if (v1 / "cpu.cfs_quota_us").exists() and os.access(v1, os.W_OK):
        return "v1", v1
    return "", None


@contextmanager
def cpu_caps(cap: float) -> Iterator[CpuCaps]:
    caps = CpuCaps(cap)
    try:
        yield caps
    finally:
        caps.close()


