"""Counters, rates, latency percentiles and rejection log lines of a running server."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque

import numpy as np

log = logging.getLogger("sogm_service.rejections")

_LATENCY_WINDOW = 2048
_RATE_WINDOW_S = 10.0


class Stats:
    """What ``<prefix>/<map>/stats`` reports: counters, rejections per reason, latencies."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.started = time.monotonic()
        self.counters: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self._latency: dict[str, deque[float]] = {}
        self._fused_times: deque[float] = deque()

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def reject(self, reason: str) -> None:
        with self._lock:
            self.rejected[reason] += 1
            self.counters["isms_rejected"] += 1

    def fused(self) -> None:
        now = time.monotonic()
        with self._lock:
            self.counters["isms_fused"] += 1
            self._fused_times.append(now)
            while self._fused_times and now - self._fused_times[0] > _RATE_WINDOW_S:
                self._fused_times.popleft()

    def latency(self, name: str, seconds: float) -> None:
        with self._lock:
            self._latency.setdefault(name, deque(maxlen=_LATENCY_WINDOW)).append(seconds)

    def isms_per_s(self) -> float:
        now = time.monotonic()
        with self._lock:
            recent = [t for t in self._fused_times if now - t <= _RATE_WINDOW_S]
        span = min(_RATE_WINDOW_S, max(now - self.started, 1e-3))
        return len(recent) / span

    def percentiles(self) -> dict[str, dict[str, float]]:
        """Per operation: count, median, p90, p99 and max, in milliseconds."""
        with self._lock:
            snapshot = {k: np.array(v) * 1e3 for k, v in self._latency.items() if v}
        return {
            k: {"count": float(v.size), "p50": float(np.percentile(v, 50)),
                "p90": float(np.percentile(v, 90)), "p99": float(np.percentile(v, 99)),
                "max": float(v.max())}
            for k, v in snapshot.items()
        }

    def snapshot(self) -> tuple[dict[str, int], dict[str, int]]:
        with self._lock:
            return dict(self.counters), dict(self.rejected)


class Rejections:
    """Counts each refusal by reason and logs it in one line, at most one a second per reason
    (the rest are counted and their number said with the next line)."""

    def __init__(self, stats: Stats, text_chars: int = 200) -> None:
        self._stats = stats
        self._text_chars = text_chars
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def reject(self, reason: str, text: str) -> None:
        self._stats.reject(reason)
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(reason, -1e9) < 1.0:
                self._suppressed[reason] = self._suppressed.get(reason, 0) + 1
                return
            extra = self._suppressed.pop(reason, 0)
            self._last[reason] = now
        more = f" ({extra} more of this reason suppressed)" if extra else ""
        log.warning("rejected ISM [%s]: %s%s", cut(reason, 64), cut(text, self._text_chars),
                    more)


def cut(text: str, limit: int = 200) -> str:
    """``text`` cut to ``limit`` characters (attacker strings in log lines), saying how much
    was left out."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}...[{len(text) - limit} more characters]"
