"""``flood``: sub-map latency while the server is offered at least twice what it can fuse.

Two publisher processes put 128x128 ``prob_u8`` ISMs from 8 robots each as fast as the link
takes them (congestion control BLOCK) for the row's duration, while a client asks for the
``mixed_fleet`` query (256x256x4 rotated biodds, 10 Hz).  The same queries are timed idle
before.  What the publishers offer is measured in the same run: their free-running rate into a
subscriber that only counts (no decoding, no fusion), against the rate the server fuses under
the flood (its capacity).  Target: loaded p99 <= 4x idle p99 at an offered rate >= 2x the
capacity, and every published ISM fused or counted by reason (``isms_rejected``,
``isms_dropped_*``), none lost silently.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

from sogm_service.bench import transport
from sogm_service.bench.core import Row, median, percentile
from sogm_service.bench.fleet import _timed_queries
from sogm_service.bench.zbench import (
    PY,
    Proc,
    _fill_layers,
    bench_layers,
    helper,
    map_server,
)
from sogm_service.client.mapclient import MapClient

PUBLISHERS = 2
SIZE = 128


def _publishers(d: Path, endpoint: str, tag: str) -> list[Proc]:
    how = transport.current()
    owner = ["--owner", how.robot] if how.client_config else []
    procs = [Proc([PY, "-m", "sogm_service.bench.procs", "flood", "--connect", endpoint,
                   "--size", str(SIZE), "--seed", str(k), "--layers", ",".join(bench_layers()),
                   *owner, *how.client_args()], d / f"flood-{tag}{k}.log", stdin=True)
             for k in range(PUBLISHERS)]
    for p in procs:
        p.expect("ready", 60.0)
    return procs


def _flood(procs: list[Proc], seconds: float) -> list[tuple[int, float, float]]:
    """Every publisher floods for ``seconds``: (sent, t_first, t_last) each."""
    for p in procs:
        p.send(f"{seconds}")
    out = []
    for p in procs:
        n, t0, t1 = p.expect("sent", seconds * 20 + 120)
        out.append((int(n), float(t0), float(t1)))
    return out


def _offered(d: Path, seconds: float) -> float:
    """ISMs/s the publishers put into a subscriber that only counts them."""
    endpoint = transport.current().endpoint()
    with helper(d, "counter", "--listen", endpoint, "--key", "ism/**", "--count",
                str(10**9)):
        procs = _publishers(d, endpoint, "raw")
        try:
            sent = _flood(procs, seconds)
        finally:
            for p in procs:
                p.stop()
    return sum(n / max(t1 - t0, 1e-9) for n, t0, t1 in sent)


def flood(quick: bool) -> Row:
    seconds = 3.0 if quick else 20.0
    with tempfile.TemporaryDirectory(prefix="sogm-bench-") as tmp:
        d = Path(tmp)
        offered = _offered(d, min(seconds, 5.0))
        with map_server(d) as served:
            client = served.client
            _fill_layers(client, 4)
            idle = _timed_queries(client, seconds / 2)
            procs = _publishers(d, served.endpoint, "server")
            try:
                before = client.stats().counters
                sent: list[tuple[int, float, float]] = []
                busy = threading.Event()
                busy.set()

                def run() -> None:
                    sent.extend(_flood(procs, seconds))
                    busy.clear()

                thread = threading.Thread(target=run, name="bench-flood")
                thread.start()
                loaded = _timed_queries(client, seconds, busy)
                thread.join()
                during = client.stats().counters
                published = sum(n for n, _, _ in sent)
                # The publishers stay until the server has everything: a session closed
                # with puts still in its send queue would lose them on the bench's side.
                after = _wait_handled(client, _handled(before) + published)
            finally:
                for p in procs:
                    p.stop()
            idle_after = _timed_queries(client, seconds / 4)
            stats = client.stats()
    span = max(t1 for _, _, t1 in sent) - min(t0 for _, t0, _ in sent)
    capacity = (during.get("isms_fused", 0) - before.get("isms_fused", 0)) / span
    row = _row(idle + idle_after, loaded, offered, capacity, published, before, after,
               stats.latency_ms.get("submap", {}))
    row.details["rx_waiting_max"] = float(stats.extra.get("rx_waiting_max", 0))
    return row


def _wait_handled(client: MapClient, n: int, timeout: float = 120.0) -> dict[str, int]:
    """The server's counters once it has handled ``n`` ISMs (or after ``timeout``)."""
    deadline = time.monotonic() + timeout
    while True:
        counters = client.stats().counters
        if _handled(counters) >= n or time.monotonic() > deadline:
            return counters
        time.sleep(0.05)


def _handled(counters: dict[str, int]) -> int:
    """ISMs fused, rejected (by reason) or dropped (by policy)."""
    return counters.get("isms_fused", 0) + _counted(counters)


def _counted(counters: dict[str, int]) -> int:
    return counters.get("isms_rejected", 0) + sum(
        v for k, v in counters.items() if k.startswith("isms_dropped"))


def _row(idle: list[float], loaded: list[float], offered: float, capacity: float,
         published: int, before: dict[str, int], after: dict[str, int],
         handler: dict[str, float]) -> Row:
    idle_p50, idle_p99 = median(idle) * 1e3, percentile(idle, 99) * 1e3
    p50, p99 = median(loaded) * 1e3, percentile(loaded, 99) * 1e3
    fused = after.get("isms_fused", 0) - before.get("isms_fused", 0)
    counted = _counted(after) - _counted(before)
    ratio, over = p99 / idle_p99, offered / capacity
    accounted = fused + counted == published
    return Row("flood", p99, idle_p99, "ms p99", ratio,
               "p99 <= 4x idle p99 at >= 2x capacity; fused + counted = published",
               ratio <= 4.0 and over >= 2.0 and accounted,
               f"the same sub-map queries idle (p50 {idle_p50:.2f} ms)",
               f"{PUBLISHERS} publishers x 8 robots, {SIZE}x{SIZE} ISMs, BLOCK: offered "
               f"{offered:.0f} ISM/s = {over:.1f}x the capacity ({capacity:.0f} ISM/s fused "
               f"under the flood); loaded p50 {p50:.2f} ms, max {max(loaded) * 1e3:.1f} ms; "
               f"published {published} = fused {fused} + counted {counted}; received "
               f"{after.get('isms_received', 0) - before.get('isms_received', 0)}"
               f"{'' if accounted else ' (NOT ACCOUNTED)'}",
               {"idle_p50_ms": idle_p50, "idle_p99_ms": idle_p99, "loaded_p50_ms": p50,
                "loaded_p99_ms": p99, "loaded_max_ms": max(loaded) * 1e3,
                "offered_isms_per_s": offered, "capacity_isms_per_s": capacity,
                "offered_over_capacity": over, "published": float(published),
                "fused": float(fused), "counted": float(counted),
                "server_handler_p50_ms": handler.get("p50", 0.0),
                "server_handler_p99_ms": handler.get("p99", 0.0),
                **{f"after_{k}": float(v) for k, v in after.items()
                   if k.startswith(("isms_dropped", "isms_rejected", "isms_shed"))}})
