"""``mixed_fleet``: sub-map latency while a fleet streams ISMs, beside the same queries idle.

The service's everyday job on one machine: a paced fleet (8 robots x 4 ISM keys, 256x256
rotated ``prob_u8``, congestion control BLOCK) publishes into one ``serve`` process at 320 and
960 ISM/s and at half the ingestion capacity measured in the same run, while a client asks for
a 256x256x4 rotated biodds sub-map at 10 Hz.  The same queries are timed idle before.  Target
at every rate: loaded p99 <= 2x idle p99, and no ISM lost.

Two rows: ``mixed_fleet``, whose robots all write the four layers the query reads, and
``mixed_fleet_per_robot``, whose robots each write their own four (keys
``ism/robot<r>/layer<l>``, 32 layers beside the query's four in the same tiles): a query's
cost must follow the layers it names, not the layers the tiles hold.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

from sogm_service.bench import transport
from sogm_service.bench.core import Row, median, percentile
from sogm_service.bench.zbench import (
    PY,
    Proc,
    Served,
    _fill_layers,
    _publisher,
    bench_layers,
    map_server,
    wait_fused,
    window,
)
from sogm_service.client.mapclient import MapClient

QUERY_HZ = 10.0


def _timed_queries(client: MapClient, seconds: float, busy: threading.Event | None = None
                   ) -> list[float]:
    """Sub-map latencies at ``QUERY_HZ`` for ``seconds`` (or while ``busy`` is set)."""
    out: list[float] = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end or (busy is not None and busy.is_set()):
        t0 = time.perf_counter()
        client.submap(**window())
        out.append(time.perf_counter() - t0)
        time.sleep(max(0.0, 1.0 / QUERY_HZ - (time.perf_counter() - t0)))
        if busy is not None and not busy.is_set() and time.monotonic() >= t_end:
            break
    return out


def _capacity(d: Path, served: Served, count: int) -> float:
    """ISMs/s the server fuses from a lossless burst (publisher as fast as it can)."""
    endpoint, client = served.endpoint, served.client
    before = client.stats().counters.get("isms_fused", 0)
    pub = _publisher(d, endpoint, transport.current().ism_key("capacity/obstacle"), count)
    try:
        pub.send("go")
        t_first = float(pub.expect("sent", 300.0)[0])
        t_done, _ = wait_fused(client, before + count)
    finally:
        pub.stop()
    return count / (t_done - t_first)


def _loaded(pace: Proc, client: MapClient, rate: float, seconds: float) -> tuple[list[float], int]:
    """Queries while ``pace`` publishes ``rate`` ISM/s for ``seconds``: latencies, ISMs sent."""
    busy = threading.Event()
    busy.set()
    sent: list[int] = []

    def publish() -> None:
        pace.send(f"{rate} {seconds}")
        sent.append(int(pace.expect("sent", seconds * 10 + 60)[0]))
        busy.clear()

    thread = threading.Thread(target=publish, name="bench-pace")
    thread.start()
    latencies = _timed_queries(client, seconds, busy)
    thread.join()
    return latencies, sent[0]


def mixed_fleet(quick: bool) -> Row:
    """The fleet writes the query's own four layers."""
    return _mixed(quick, per_robot=False)


def mixed_fleet_per_robot(quick: bool) -> Row:
    """Every robot writes its own four layers (32 in all); the query names its four."""
    return _mixed(quick, per_robot=True)


def _mixed(quick: bool, per_robot: bool) -> Row:
    seconds = 2.0 if quick else 10.0
    with tempfile.TemporaryDirectory(prefix="sogm-bench-") as tmp, \
            map_server(Path(tmp)) as served:
        d, client = Path(tmp), served.client
        _fill_layers(client, 4)
        idle = _timed_queries(client, seconds)
        capacity = _capacity(d, served, 300 if quick else 1500)
        how = transport.current()
        owner = ["--owner", how.robot] if how.client_config else []
        layers = ["--per-robot"] if per_robot else ["--layers", ",".join(bench_layers())]
        pace = Proc([PY, "-m", "sogm_service.bench.procs", "paced", "--connect",
                     served.endpoint, *layers, *owner, *how.client_args()], d / "paced.log",
                    stdin=True)
        results = {}
        try:
            pace.expect("ready", 60.0)
            published = 0
            for rate in (320.0, 960.0, round(capacity / 2)):
                fused_before = client.stats().counters.get("isms_fused", 0)
                latencies, sent = _loaded(pace, client, rate, seconds)
                published += sent
                _, counters = wait_fused(client, fused_before + sent)
                results[rate] = (latencies, counters.get("isms_fused", 0) - fused_before, sent)
        finally:
            pace.stop()
        idle_after = _timed_queries(client, seconds / 2)
        stats = client.stats()
    row = _row(idle + idle_after, results, capacity,
               "mixed_fleet_per_robot" if per_robot else "mixed_fleet")
    handler = stats.latency_ms.get("submap", {})
    row.details.update({"layers": float(stats.extra.get("layers", 0)),
                        "server_handler_p50_ms": handler.get("p50", 0.0),
                        "server_handler_p99_ms": handler.get("p99", 0.0)})
    return row


def _row(idle: list[float], results: dict[float, tuple[list[float], int, int]],
         capacity: float, name: str = "mixed_fleet") -> Row:
    idle_p50, idle_p99 = median(idle) * 1e3, percentile(idle, 99) * 1e3
    details: dict[str, float | str] = {"idle_p50_ms": idle_p50, "idle_p99_ms": idle_p99,
                                       "capacity_isms_per_s": capacity}
    parts, worst, lost = [], 0.0, 0
    for rate, (lat, fused, sent) in results.items():
        p50, p99 = median(lat) * 1e3, percentile(lat, 99) * 1e3
        worst = max(worst, p99 / idle_p99)
        lost += sent - fused
        details.update({f"r{rate:.0f}_p50_ms": p50, f"r{rate:.0f}_p99_ms": p99,
                        f"r{rate:.0f}_lost": float(sent - fused)})
        parts.append(f"{rate:.0f} ISM/s: p50 {p50:.2f} / p99 {p99:.2f} ms ({p99 / idle_p99:.2f}x)")
    return Row(name, worst * idle_p99, idle_p99, "ms p99", worst,
               "loaded p99 <= 2x idle p99 at every rate, none lost", worst <= 2.0 and lost == 0,
               f"the same sub-map queries idle (p50 {idle_p50:.2f} ms)",
               "; ".join(parts) + f"; capacity {capacity:.0f} ISM/s; lost {lost}", details)
