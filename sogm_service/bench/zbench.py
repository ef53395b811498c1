"""Benchmarks through real Zenoh sessions and processes: submap, ingestion, memory, start-up.

Every process here is started with ``subprocess`` (never forked after a session exists) and
ended by its own pid; sessions listen and connect on 127.0.0.1 only, multicast scouting off.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from sogm_service.bench import transport
from sogm_service.bench.compute import MAP_RES, synthetic_ism
from sogm_service.bench.core import Row, interleaved, median, percentile
from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import open_session, wait_listening
from sogm_service.core.geometry import Pose2D
from sogm_service.service.server import pipeline as ingest
from sogm_service.wire.queries import StatsReply

PY = sys.executable


class Proc:
    """A child process this benchmark started (and alone ends, by pid)."""

    def __init__(self, args: list[str], log: Path, stdin: bool = False) -> None:
        self.log_path = log
        self._log = open(log, "wb")  # noqa: SIM115 - lives as long as the process
        self.popen = subprocess.Popen(
            args, stdout=subprocess.PIPE, stderr=self._log,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1"}, text=True)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def line(self, timeout: float = 30.0) -> str:
        """Next stdout line (raises if the process dies or stays silent)."""
        out: list[str] = []
        stdout = self.popen.stdout
        assert stdout is not None
        reader = threading.Thread(target=lambda: out.append(stdout.readline()), daemon=True)
        reader.start()
        reader.join(timeout)
        if not out or not out[0]:
            raise RuntimeError(f"{self.popen.args!r} said nothing:\n{self.tail()}")
        return out[0].strip()

    def expect(self, word: str, timeout: float = 30.0) -> list[str]:
        while True:
            parts = self.line(timeout).split()
            if parts and parts[0] == word:
                return parts[1:]

    def send(self, text: str) -> None:
        stdin = self.popen.stdin
        assert stdin is not None
        stdin.write(text + "\n")
        stdin.flush()

    def tail(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")[-3000:]

    def stop(self, timeout: float = 15.0) -> None:
        if self.popen.stdin is not None:
            self.popen.stdin.close()
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
        try:
            self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            self.popen.wait(5)
        self._log.close()


def _config(directory: Path, listen: str, queue_size: int = 64) -> Path:
    path = directory / "server.toml"
    path.write_text(f'[map]\nresolution = {MAP_RES}\n\n[zenoh]\nlisten = ["{listen}"]\n'
                    f'{transport.current().server_toml()}\n'
                    f'[limits]\nqueue_size = {queue_size}\n'
                    + (f'fuse_workers = {os.environ["SOGM_BENCH_WORKERS"]}\n'
                       if os.environ.get("SOGM_BENCH_WORKERS") else ""),
                    encoding="utf-8")
    return path


@dataclass
class Served:
    proc: Proc
    client: MapClient
    endpoint: str


@contextmanager
def map_server(directory: Path) -> Iterator[Served]:
    """A ``sogm-service serve`` process and a client connected to it, once discoverable."""
    how = transport.current()
    endpoint = how.endpoint()
    proc = Proc([PY, "-m", "sogm_service", "serve", "--config",
                 str(_config(directory, endpoint))], directory / "server.log")
    try:
        wait_listening(endpoint, 30.0, lambda: proc.popen.poll() is not None, proc.tail)
        with MapClient.connect(timeout=10.0, zenoh_settings=how.client(endpoint)) as client:
            deadline = time.monotonic() + 30.0
            while not client.servers(timeout=1.0):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"server not discoverable:\n{proc.tail()}")
            yield Served(proc, client, endpoint)
    finally:
        proc.stop()


@contextmanager
def helper(directory: Path, role: str, *args: str, stdin: bool = False) -> Iterator[Proc]:
    """A helper process standing in for a server (the raw baselines' queryable, counter)."""
    proc = Proc([PY, "-m", "sogm_service.bench.procs", role, *args,
                 *transport.current().server_args()],
                directory / f"{role}.log", stdin=stdin)
    try:
        proc.expect("ready")
        yield proc
    finally:
        proc.stop()


def wait_fused(client: MapClient, n: int, timeout: float = 120.0,
               interval: float = 0.01) -> tuple[float, dict[str, int]]:
    """Wall-clock time at which the server had fused or rejected ``n`` ISMs, and counters."""
    deadline = time.monotonic() + timeout
    while True:
        counters = client.stats().counters
        if counters.get("isms_fused", 0) + counters.get("isms_rejected", 0) >= n:
            return time.time(), counters
        if time.monotonic() > deadline:
            raise RuntimeError(f"only {counters} after {timeout} s")
        time.sleep(interval)


# -- submap -------------------------------------------------------------------------------
# The client's default reply encoding (prob_f32: 4 B per cell, 1 MiB for 4 layers).
WINDOW: dict[str, Any] = dict(x=12.8, y=12.8, yaw=0.5, width=256 * MAP_RES, height=256 * MAP_RES,
                              resolution=MAP_RES, interp="biodds", encoding="prob_f32")


def bench_layers() -> list[str]:
    """The four layers the sub-map benchmarks fill and ask for, by name."""
    return [transport.current().ism_key(f"layer{k}").removeprefix("ism/") for k in range(4)]


def window() -> dict[str, Any]:
    """:data:`WINDOW` naming its four layers: the same 256x256x4 reply however many layers
    other ISMs add to the map meanwhile (a fleet's own layers would otherwise grow it)."""
    return {**WINDOW, "layers": bench_layers()}


def _fill_layers(client: MapClient, layers: int) -> None:
    for k in range(layers):
        client.publish_ism(transport.current().ism_key(f"layer{k}"), synthetic_ism(512, k),
                           resolution=MAP_RES,
                           origin=Pose2D(0.0, 0.0, 0.0))
    wait_fused(client, layers)


def submap(quick: bool) -> Row:
    repeats = 30 if quick else 400
    with tempfile.TemporaryDirectory(prefix="sogm-bench-") as tmp, \
            map_server(Path(tmp)) as served:
        client = served.client
        _fill_layers(client, 4)
        size = len(client.get_raw(client.key("submap"), window()))
        how = transport.current()
        raw_ep = how.endpoint()
        # The same key as the server's queryable (another process, its own network): the
        # baseline goes through the same access control, if any.
        with helper(Path(tmp), "queryable", "--listen", raw_ep, "--key", client.key("submap"),
                    "--size", str(size)), \
                MapClient.connect(timeout=10.0, zenoh_settings=how.client(raw_ep)) as raw:
            ours, base = interleaved(lambda: client.submap(**window()),
                                     lambda: raw.get_raw(raw.key("submap")), repeats,
                                     warmup=5)
        handler = client.stats().latency_ms.get("submap", {}).get("p50", 0.0)
    server = {"server_handler_p50_ms": handler, **_breakdown_in_child(10 if quick else 50)}
    return _submap_row(ours, base, size, server)


def _breakdown_in_child(repeats: int) -> dict[str, float]:
    """:func:`submap_breakdown` in a fresh process with the server's allocator settings
    (:mod:`~sogm_service.service.server.allocator`), not the state the bench process has
    reached."""
    import json

    code = ("import json; "
            "from sogm_service.service.server.allocator import keep_large_allocations; "
            "keep_large_allocations(); from sogm_service.bench.zbench import submap_breakdown; "
            f"print(json.dumps(submap_breakdown({repeats})))")
    out = subprocess.run([PY, "-c", code], capture_output=True, text=True, check=True,
                         timeout=120)
    result: dict[str, float] = json.loads(out.stdout)
    return result


def submap_breakdown(repeats: int) -> dict[str, float]:
    """The server's share on the same map: sampling (mosaic + warp), the reply encoding
    (log-odds -> probability) and msgpack; median ms each."""
    from sogm_service.bench.compute import fresh_map, ism_message
    from sogm_service.core import logodds
    from sogm_service.core.geometry import window_geometry
    from sogm_service.service.server import queries
    from sogm_service.wire import codec
    from sogm_service.wire.queries import SubmapRequest

    tiled = fresh_map()
    for k in range(4):
        msg = ism_message(synthetic_ism(512, k), MAP_RES, Pose2D(0.0, 0.0, 0.0))
        ingest.fuse_ism(tiled, msg, f"bench/layer{k}")
    req = queries.parse_request(SubmapRequest, {k: str(v) for k, v in WINDOW.items()})
    window = window_geometry(req.x, req.y, req.yaw, req.width, req.height, MAP_RES)
    stack = tiled.sample(window, tiled.layers, "biodds")
    reply = queries.submap(tiled, req, 0.0)
    parts = {"sample_ms": lambda: tiled.sample(window, tiled.layers, "biodds"),
             "encode_reply_ms": lambda: logodds.encode_fixed(stack, "prob_f32"),
             "msgpack_ms": lambda: codec.encode(reply)}
    return {k: median(interleaved(f, lambda: None, repeats)[0]) * 1e3
            for k, f in parts.items()}


def _submap_row(ours: list[float], base: list[float], size: int,
                server: dict[str, float]) -> Row:
    m_o, m_b = median(ours) * 1e3, median(base) * 1e3
    p_o, p_b = percentile(ours, 99) * 1e3, percentile(base, 99) * 1e3
    ratio, p_ratio = m_o / m_b, p_o / p_b
    return Row("submap_zenoh_256x4", m_o, m_b, "ms", ratio, "median <= 2.5x, p99 <= 3x",
               ratio <= 2.5 and p_ratio <= 3.0,
               f"raw Zenoh get of a prepared {size}-byte payload from another process",
               f"p99 {p_o:.2f} vs {p_b:.2f} ms = {p_ratio:.2f}x; rotated 0.5 rad, biodds, "
               "prob_f32 reply (the client's default), client decode included; server handler "
               f"p50 {server['server_handler_p50_ms']:.2f} ms, of which (fresh process) "
               + ", ".join(f"{k.removesuffix('_ms')} {v:.2f} ms" for k, v in server.items()
                           if k != "server_handler_p50_ms"),
               {"p99_ms": p_o, "baseline_p99_ms": p_b, "p99_ratio": p_ratio,
                "reply_bytes": float(size), "repeats": float(len(ours)), **server})


# -- ingestion ----------------------------------------------------------------------------
def _rounds(pub: Proc, count: int, rounds: int,
            finish: Callable[[int], float]) -> list[float]:
    """Rates (ISMs/s) of ``rounds`` bursts; ``finish(k)`` returns the k-th burst's end time
    (wall clock, comparable with the publisher's across processes)."""
    rates = []
    for k in range(rounds + 1):
        pub.send("go")
        t_first = float(pub.expect("sent", 300.0)[0])
        rate = count / (finish(k + 1) - t_first)
        if k:  # burst 0 warms up connections, caches and allocators
            rates.append(rate)
    return rates


def ingestion(quick: bool) -> Row:
    count, rounds = (150, 2) if quick else (1500, 5)
    with tempfile.TemporaryDirectory(prefix="sogm-bench-") as tmp:
        d = Path(tmp)
        raw_rates = _raw_ingest(d, count, rounds)
        ours_rates, stats = _server_ingest(d, count, rounds)
    one_worker = in_process_rate(count, 3 if quick else 7)
    cores = os.cpu_count() or 1
    counters = stats.counters
    sent = count * (rounds + 1)  # with the warm-up burst
    dropped = sent - counters.get("isms_fused", 0)
    ours, base = median(ours_rates), one_worker * cores
    ratio = ours / base
    fuse_ms = stats.latency_ms.get("fuse", {})
    return Row("ingest_zenoh_256", ours, base, "ISM/s", ratio, ">= 0.8x, none dropped",
               ratio >= 0.8 and dropped == 0,
               f"one worker's in-process decode+fuse rate ({one_worker:.0f} ISM/s) x {cores} "
               "cores",
               f"median of {rounds} bursts of {count} ISMs after a warm-up burst; any heading, "
               f"biodds; not fused {dropped} (rejected {sum(stats.rejected.values())}); "
               f"server decode-to-fused p50 {fuse_ms.get('p50', 0.0):.2f} ms/ISM; old anchor "
               f"(raw puts to a counting subscriber) {median(raw_rates):.0f} ISM/s",
               {"not_fused": float(dropped), "count": float(count), "rounds": float(rounds),
                "one_worker_in_process": one_worker, "cores": float(cores),
                "old_anchor_raw_puts": median(raw_rates),
                "server_fuse_p50_ms": fuse_ms.get("p50", 0.0),
                "server_fuse_p99_ms": fuse_ms.get("p99", 0.0)})


def in_process_rate(count: int, repeats: int) -> float:
    """ISMs/s of one thread decoding and fusing the ingestion bench's payloads in process:
    the work the server does per ISM, without Zenoh or hand-offs (best of ``repeats``)."""
    from sogm_service.bench.compute import fresh_map
    from sogm_service.bench.procs import ism_payloads
    from sogm_service.wire import codec
    from sogm_service.wire.messages import IsmMessage

    payloads = ism_payloads(count, 256)
    best = 0.0
    for _ in range(repeats):
        tiled = fresh_map()
        t0 = time.perf_counter()
        for p in payloads:
            ingest.fuse_ism(tiled, codec.decode(IsmMessage, p), "bench/obstacle")
        best = max(best, count / (time.perf_counter() - t0))
    return best


def _publisher(d: Path, endpoint: str, key: str, count: int) -> Proc:
    pub = Proc([PY, "-m", "sogm_service.bench.procs", "publisher", "--connect", endpoint,
                "--key", key, "--count", str(count), *transport.current().client_args()],
               d / "publisher.log", stdin=True)
    pub.expect("ready", 60.0)
    return pub


def _raw_ingest(d: Path, count: int, rounds: int) -> list[float]:
    endpoint = transport.current().endpoint()
    with helper(d, "counter", "--listen", endpoint, "--key", "ism/**", "--count",
                str(count)) as counter:
        pub = _publisher(d, endpoint, transport.current().ism_key("obstacle"), count)
        try:
            return _rounds(pub, count, rounds,
                           lambda k: float(counter.expect("done", 300.0)[1]))
        finally:
            pub.stop()


def _server_ingest(d: Path, count: int, rounds: int) -> tuple[list[float], StatsReply]:
    with map_server(d) as served:
        client = served.client
        pub = _publisher(d, served.endpoint, transport.current().ism_key("obstacle"), count)
        try:
            rates = _rounds(pub, count, rounds, lambda k: wait_fused(client, k * count)[0])
        finally:
            pub.stop()
        return rates, client.stats()


# -- memory -------------------------------------------------------------------------------
def memory(quick: bool) -> Row:
    side, layers, piece = 2000, 8, 500  # 100 m x 100 m at 5 cm; ISMs of 25 m x 25 m
    raw_mb = side * side * layers * 2 / 1e6
    with tempfile.TemporaryDirectory(prefix="sogm-bench-") as tmp, \
            map_server(Path(tmp)) as served:
        proc, client = served.proc, served.client
        idle = _proc_status(proc.pid, "VmRSS")
        n = 0
        for k in range(layers):
            for i in range(0, side, piece):
                for j in range(0, side, piece):
                    ism = synthetic_ism(piece, n)
                    client.publish_ism(transport.current().ism_key(f"layer{k}"), ism,
                                       resolution=MAP_RES,
                                       origin=Pose2D(i * MAP_RES, j * MAP_RES, 0.0))
                    n += 1
        _, counters = wait_fused(client, n)
        stats = client.stats()
        peak, rss = _proc_status(proc.pid, "VmHWM"), _proc_status(proc.pid, "VmRSS")
    limit = 1.3 * raw_mb + 150.0
    return Row("memory_100m_5cm_8", peak, raw_mb, "MB", peak / raw_mb,
               "peak RSS <= 1.3x raw + 150 MB", peak <= limit,
               "raw int16 bytes of 8 layers x 2000 x 2000 cells",
               f"server process VmHWM; limit {limit:.0f} MB; resident tiles "
               f"{stats.extra.get('tiles_resident')}, {stats.extra.get('resident_mb')} MB; "
               f"RSS idle {idle:.0f} MB, at the end {rss:.0f} MB",
               {"limit_mb": limit, "rss_idle_mb": idle, "rss_end_mb": rss, "isms": float(n),
                "fused": float(counters.get("isms_fused", 0))})


def _proc_status(pid: int, field: str) -> float:
    """A ``kB`` field of ``/proc/<pid>/status`` in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return float(line.split()[1]) * 1024 / 1e6
    raise RuntimeError(f"no {field} for pid {pid}")


# -- start-up -----------------------------------------------------------------------------
def startup(quick: bool) -> Row:
    repeats = 2 if quick else 5
    ours, base = [], []
    with tempfile.TemporaryDirectory(prefix="sogm-bench-") as tmp:
        for _ in range(repeats):
            base.append(_import_time())
            ours.append(_serve_time(Path(tmp)))
    m_o, m_b = median(ours), median(base)
    return Row("startup_serve", m_o * 1e3, m_b * 1e3, "ms", m_o / m_b, "< 2 s", m_o < 2.0,
               'python -c "import zenoh"',
               "from spawning serve to its liveliness token seen by a client",
               {"repeats": float(repeats), "max_ms": max(ours) * 1e3})


def _wait_token(seen: threading.Event, proc: Proc, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not seen.wait(0.005):
        if proc.popen.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"no liveliness token from serve:\n{proc.tail()}")


def _import_time() -> float:
    t0 = time.perf_counter()
    subprocess.run([PY, "-c", "import zenoh"], check=True)
    return time.perf_counter() - t0


def _serve_time(d: Path) -> float:
    """The client listens and the server connects to it, so the token's arrival is the moment
    the server became discoverable (no polling delay)."""
    how = transport.current()
    ours_ep = how.endpoint()
    seen = threading.Event()
    session = open_session(how.server(ours_ep))  # an observer with a server's identity
    try:
        sub = session.liveliness().declare_subscriber(
            "sogm/default/@server/*",
            lambda s: seen.set() if s.kind == zenoh.SampleKind.PUT else None)
        t0 = time.perf_counter()
        proc = Proc([PY, "-m", "sogm_service", "serve", "--listen", how.endpoint(),
                     "--connect", ours_ep, *how.server_args()], d / "startup.log")
        try:
            _wait_token(seen, proc)
            elapsed = time.perf_counter() - t0
        finally:
            proc.stop()
        sub.undeclare()
    finally:
        session.close()
    return elapsed
