"""The ``cluster_scale`` row: ingestion of 1, 2 and 3 cluster members, each held to the same CPU
share, as if each ran on a host of its own.

Each member is a ``sogm-service serve`` with ``[cluster] enabled`` in a cgroup of its own whose
CPU quota is the cap (``cpu.max`` of cgroup v2, or ``cpu.cfs_quota_us`` of the v1 ``cpu``
controller, :mod:`~sogm_service.bench.cgroups`), placed right after it starts so its every
thread is under it; its CPU time is read from its cgroup.  The Zenoh router
and the publisher stand outside the caps (in a group of the same weight without a quota), for
the network and the fleet.  The publisher (a process of its own, ``python -m
sogm_service.bench.cluster_scale publish``) puts 252x252 aligned ``prob_u8`` ISMs, each
inside one tile of a 32 x 32 tile area, zstd-compressed as
:class:`~sogm_service.client.mapclient.MapClient` sends them by default, as fast as the router
takes them (BLOCK): more than the cluster fuses, so the members' pace is the measure.  The
rate is a batch's size over the time until every member has handled it (``isms_fused`` of
each member's ``stats``, asked over a session connected to that member alone), after every
member reports its supercell kernels ready (:func:`_kernels_ready`) and after a warm-up
batch: an ISM counts once all its owners have fused it and the others have checked
its header (:func:`measure`).  Without a cgroup CPU controller
the row runs uncapped and says so.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np

from sogm_service.bench import transport
from sogm_service.bench.cgroups import CpuCaps, cpu_caps
from sogm_service.bench.cluster import RES, _server_id
from sogm_service.bench.core import Row, median
from sogm_service.bench.zbench import PY, Proc
from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import open_session, wait_listening
from sogm_service.wire.errors import ClientError
from sogm_service.wire.keys import MapKeys

CAP_CPU = 0.25
"""Each member's CPU share, in cores: 3 members (0.75 cores) leave the rest of this 2-core
machine to the router and the publisher (with 0.4 each, 3 members got 0.16 of their 0.4)."""
TILES = 32
"""The publisher's area, in tiles a side: each member's share of the ISMs is its share of
these tiles under the rendezvous ownership, a draw that varies with the members' ids; over
1024 tiles the busiest of 3 members owns a median 35 % of them (36 % over 256), and the
busiest paces the cluster."""
SPAN = 256 * RES  # a tile's side in metres
ISM_CELLS = 252  # an ISM's side: inside one tile (see payloads)
WARM_ISMS = 3 * TILES * TILES
"""The warm-up batch: every tile of the area three times (created, then updated)."""
BATCH = 5000
"""ISMs per member in a measured batch (about 5-10 s at the rates measured here)."""
BATCH_QUICK = 1000
ROUNDS = 5
"""Rounds of every configuration, interleaved; the row reports each one's median (members
start afresh each round, so each round draws new ids and new ownership shares)."""
POLL_S = 0.05  # how often the members are asked whether they have handled a batch


# -- one measurement --------------------------------------------------------------------------
def _start_member(d: Path, name: str, router: str, replicas: int) -> tuple[Proc, str]:
    """A member and its endpoint; :func:`measure` caps it once it listens (its start-up,
    imports and kernels, is not what the row measures and took 4x as long under the cap)."""
    how = transport.current()
    endpoint = how.endpoint()
    cfg = d / f"{name}.toml"
    cfg.write_text(f'[map]\nresolution = {RES}\n[cluster]\nenabled = true\nreplicas = {replicas}\n'
                   f'[zenoh]\nlisten = ["{endpoint}"]\nconnect = ["{router}"]\n'
                   + how.server_toml(), encoding="utf-8")
    proc = Proc([PY, "-m", "sogm_service", "serve", "--config", str(cfg)], d / f"{name}.log")
    return proc, endpoint


def _ended(proc: Proc) -> Callable[[], bool]:
    return lambda: proc.popen.poll() is not None


def _cpu_s(pid: int) -> float:
    """CPU seconds process ``pid``'s live threads have run (the scheduler's own accounting,
    ``/proc/<pid>/task/*/schedstat``: exact, where the tick-sampled ``stat`` times are biased
    by a quota's throttling)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with suppress(OSError, ValueError, IndexError):  # a thread that just ended
            total += int((task / "schedstat").read_text().split()[0])
    return total / 1e9


def _stats(client: MapClient, member: str, timeout: float = 10.0) -> dict[str, Any]:
    """Member ``member``'s ``stats``, asked under its own key over ``client`` (a session
    connected to that member alone)."""
    import msgpack

    key = MapKeys(client.prefix, client.map_name).member(member, "stats")
    got: dict[str, Any] = msgpack.unpackb(client.get_raw(key, {}, timeout=timeout))
    return got


def _counters(direct: dict[str, MapClient]) -> dict[str, tuple[int, int]]:
    """Each member's (``isms_fused``, ``cluster_isms_elsewhere``)."""
    out = {}
    for member, client in direct.items():
        counters = _stats(client, member)["counters"]
        out[member] = (int(counters.get("isms_fused", 0)),
                       int(counters.get("cluster_isms_elsewhere", 0)))
    return out


def _kernels_ready(direct: dict[str, MapClient], timeout: float) -> None:
    """Wait until every member has its supercell kernels ready.  Each member compiles or
    loads them in a child process at start (in its cgroup: 1 s of CPU from the cache, 10 s
    when it compiles); offered ISMs meanwhile, a member shares its cap with that child, and a
    member starved that way was seen never handling the warm-up batch the publisher had put.
    A member whose queryables a fresh session does not know yet does not answer: asked
    again."""
    deadline = time.monotonic() + timeout
    waiting = set(direct)
    while True:
        for member in sorted(waiting):
            with suppress(ClientError):
                if _stats(direct[member], member, timeout=2.0)["extra"].get("kernels_ready"):
                    waiting.discard(member)
        if not waiting:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"cluster_scale: {len(waiting)} member(s) without their "
                               f"kernels after {timeout:g} s")
        time.sleep(POLL_S)


def _cpu(caps: CpuCaps, ids: dict[str, tuple[int, str]]) -> list[float]:
    """CPU seconds each member has used (its cgroup's count, else its threads')."""
    out = []
    for pid, name in ids.values():
        used = caps.usage_s(name)
        out.append(_cpu_s(pid) if used is None else used)
    return out


@contextmanager
def _direct_clients(endpoints: dict[str, str]) -> Iterator[dict[str, MapClient]]:
    """A client session connected to each member's own endpoint: its stats come back at once
    even while the ISMs from the router queue up (a queue that pushes back holds that link,
    and a query sent through the router waits behind the ISMs for seconds)."""
    how = transport.current()
    clients: dict[str, MapClient] = {}
    try:
        for member, endpoint in endpoints.items():
            clients[member] = MapClient(open_session(how.client(endpoint)))
        yield clients
    finally:
        for client in clients.values():
            client.close()


def _handled_by_all(direct: dict[str, MapClient], count: int, timeout: float) -> float:
    """Poll until every member has handled ``count`` ISMs; the time it was first seen."""
    deadline = time.monotonic() + timeout
    while True:
        now = time.monotonic()
        if min(fused for fused, _ in _counters(direct).values()) >= count:
            return now
        if now > deadline:
            raise RuntimeError(f"cluster_scale: the members did not handle {count} ISMs "
                               f"within {timeout:g} s")
        time.sleep(POLL_S)


def measure(members: int, replicas: int, caps: CpuCaps, batch_per_member: int
            ) -> dict[str, Any]:
    """The cluster's ISMs per second with ``members`` capped members, and each member's share
    of the ISMs it fused (not just checked).

    A warm-up batch (every tile created, every code path run) is handled by every member
    first; then a batch of ``batch_per_member`` ISMs per member is published as fast as the
    members take it (BLOCK), and the rate is its size over the time from its
    first put until every member has handled it (an ISM counts once all its owners have
    fused it and the others have checked its header).  Both ends have empty queues, so no
    ISM buffered in a queue or a socket is counted or missed.  The members are asked over a
    session connected to each alone: through the router a query waits behind the ISMs."""
    how = transport.current()
    with tempfile.TemporaryDirectory(prefix="sogm-bench-scale-") as tmp:
        d = Path(tmp)
        router_ep = how.endpoint()
        procs = [Proc([PY, "-m", "sogm_service", "router", "--listen", router_ep,
                       *how.server_args()], d / "router.log")]
        try:
            caps.place("feeders", procs[0].pid, capped=False)
            wait_listening(router_ep, 30.0, lambda: procs[0].popen.poll() is not None,
                           procs[0].tail)
            started = [_start_member(d, f"member{k}", router_ep, min(replicas, members))
                       for k in range(members)]  # start side by side
            procs += [proc for proc, _ in started]
            ids, endpoints = {}, {}
            for k, (proc, endpoint) in enumerate(started):
                wait_listening(endpoint, 60.0, _ended(proc), proc.tail)
                caps.place(f"member{k}", proc.pid)  # capped before any ISM is offered
                member = _server_id(proc)
                ids[member] = (proc.pid, f"member{k}")
                endpoints[member] = endpoint
            pub = Proc([PY, "-m", "sogm_service.bench.cluster_scale", "publish", "--connect",
                        router_ep, "--key", how.ism_key("obstacle"), *how.client_args()],
                       d / "publisher.log", stdin=True)
            procs.append(pub)
            caps.place("feeders", pub.pid, capped=False)
            pub.expect("ready", 60.0)
            with MapClient(open_session(how.client(router_ep))) as client, \
                    _direct_clients(endpoints) as direct:
                deadline = time.monotonic() + 60
                while len(client.servers(timeout=1.0)) < members and \
                        time.monotonic() < deadline:
                    time.sleep(0.1)
                _kernels_ready(direct, 180.0)
                time.sleep(1.0)  # the members' own handovers settle
                pub.send(str(WARM_ISMS))
                _handled_by_all(direct, WARM_ISMS, 120.0)
                batch = batch_per_member * members
                before, cpu0, t0 = _counters(direct), _cpu(caps, ids), time.monotonic()
                pub.send(str(batch))
                t1 = _handled_by_all(direct, WARM_ISMS + batch, 60.0 + batch / 20.0)
                after, cpu1 = _counters(direct), _cpu(caps, ids)
        finally:
            for proc in reversed(procs):
                proc.stop()
    dt = t1 - t0
    other = [after[m][1] - before[m][1] for m in ids]
    own = [(after[m][0] - before[m][0]) - e for m, e in zip(ids, other, strict=True)]
    cpu = [b - a for a, b in zip(cpu0, cpu1, strict=True)]
    return {"rate": batch / dt, "owned_share_min": min(own) / max(1, sum(own)),
            "owned_share_max": max(own) / max(1, sum(own)), "sent": float(batch),
            "cpu_per_member": sum(cpu) / len(cpu) / dt,
            "samples": list(zip(own, other, cpu, strict=True))}


def cluster_scale(quick: bool) -> Row:
    per_member, rounds = (BATCH_QUICK, 1) if quick else (BATCH, ROUNDS)
    # --quick (the test suite's smoke run) runs 1 and 2 members, replicas 1
    configs = [(1, 1), (2, 1)] + ([] if quick else [(3, 1), (2, 2), (3, 2)])
    runs: dict[tuple[int, int], list[dict[str, Any]]] = {c: [] for c in configs}
    load0 = os.getloadavg()[0]
    with cpu_caps(CAP_CPU) as caps:
        for _ in range(rounds):  # interleaved: load changes hit every configuration alike
            for n, r in configs:
                runs[(n, r)].append(measure(n, r, caps, per_member))
        cap = caps.describe()
        capped = caps.available
    load1 = os.getloadavg()[0]
    rate = {c: median([m["rate"] for m in ms]) for c, ms in runs.items()}
    one = rate[(1, 1)]
    s = {c: rate[c] / one for c in configs}
    passed = (s[(2, 1)] >= 1.6 and s[(3, 1)] >= 2.2) if capped and not quick else None
    fused_s, checked_s = costs([x for (_, r), ms in runs.items() if r == 1
                                for m in ms for x in m["samples"]])
    cpu = {c: median([m["cpu_per_member"] for m in ms]) for c, ms in runs.items()}
    details: dict[str, float | str] = {}
    if not quick:
        details = {"speedup_3": s[(3, 1)], "rate_3": rate[(3, 1)],
                   "cpu_per_member_3": cpu[(3, 1)],
                   "speedup_2_replicas_2": s[(2, 2)], "speedup_3_replicas_2": s[(3, 2)],
                   "rate_2_replicas_2": rate[(2, 2)], "rate_3_replicas_2": rate[(3, 2)]}
    three = "3 members and replicas 2 not run (--quick)" if quick else (
        f"3 members {rate[(3, 1)]:.0f} ISM/s ({s[(3, 1)]:.2f}x); replicas 2: 2/3 members "
        f"{rate[(2, 2)]:.0f}/{rate[(3, 2)]:.0f} ISM/s ({s[(2, 2)]:.2f}x, {s[(3, 2)]:.2f}x)")
    per_round = "; ".join(f"{n} members replicas {r}: "
                          + "/".join(f"{m['rate']:.0f}" for m in runs[(n, r)])
                          for n, r in configs)
    shares = ", ".join(f"{n}: {runs[(n, 1)][-1]['owned_share_min']:.2f}-"
                       f"{runs[(n, 1)][-1]['owned_share_max']:.2f}"
                       for n in (2, 3) if (n, 1) in runs)
    return Row("cluster_scale", rate[(2, 1)], one, "ISM/s", s[(2, 1)],
               ">= 1.6x with 2 members, >= 2.2x with 3 (replicas 1)", passed,
               f"one cluster member held to {CAP_CPU:g} CPU",
               f"{cap}; router and publisher uncapped; {ISM_CELLS}x{ISM_CELLS} aligned ISMs, each "
               f"inside one of {TILES}x{TILES} tiles, zstd as MapClient sends them, offered "
               f"faster than fused (BLOCK); rate = a batch of {per_member} ISMs per member over "
               f"the time until every member handled it, after {WARM_ISMS} ISMs of warm-up, "
               f"median of {rounds}; replicas 1: 1/2 members {one:.0f}/{rate[(2, 1)]:.0f} ISM/s "
               f"({s[(2, 1)]:.2f}x); {three}; share of the fused ISMs per member {shares}; "
               f"a member's CPU {fused_s * 1e6:.0f} us per ISM it fuses, "
               f"{checked_s * 1e6:.0f} us per ISM it only checks (fitted); CPU per member 1/2: "
               f"{cpu[(1, 1)]:.2f}/{cpu[(2, 1)]:.2f}; ISM/s per round: {per_round}; load average "
               f"{load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores",
               {"speedup_2": s[(2, 1)], **details, "cap": cap,
                "cap_cpu": CAP_CPU if capped else 0.0, "rate_1": one, "rate_2": rate[(2, 1)],
                "cpu_us_per_fused_ism": fused_s * 1e6, "cpu_us_per_checked_ism": checked_s * 1e6,
                "cpu_per_member_1": cpu[(1, 1)], "cpu_per_member_2": cpu[(2, 1)],
                "rates_per_round": per_round,
                "load_start": load0, "load_end": load1})


def costs(samples: list[tuple[int, int, float]]) -> tuple[float, float]:
    """A member's CPU seconds per ISM it fuses and per ISM it only checks (another member's),
    fitted by least squares to every member's (fused, checked, CPU seconds) of a window."""
    a = np.array([[o, e] for o, e, _ in samples], float)
    b = np.array([c for _, _, c in samples], float)
    (fused, checked), *_ = np.linalg.lstsq(a, b, rcond=None)
    return float(fused), float(checked)


# -- the publisher process --------------------------------------------------------------------
def payloads() -> list[bytes]:
    """One encoded ``prob_u8`` ISM inside each tile of the area, in an order that visits the
    area's tiles far apart in turn.  Each is 252x252 cells, 2 cells in from its tile's edges:
    a grid of the tile's full 256 cells would also meet the tile's neighbours (a footprint
    includes the cells on its edges), so every ISM would have up to 4 tiles' owners."""
    from sogm_service.bench.compute import ism_message, synthetic_ism
    from sogm_service.core.geometry import Pose2D
    from sogm_service.wire import codec

    codes = [synthetic_ism(ISM_CELLS, s) for s in range(4)]
    out = []
    for k in range(TILES * TILES):
        tile = (k * 97) % (TILES * TILES)  # 97 is odd, the count a power of 2: each tile once
        i, j = tile % TILES, tile // TILES
        inset = (256 - ISM_CELLS) / 2 * RES
        msg = ism_message(codes[k % 4], RES, Pose2D(i * SPAN + inset, j * SPAN + inset, 0.0))
        out.append(codec.encode(msg.model_copy(update={"stamp": float(k)}).compressed()))
    return out


def run_publisher(argv: list[str]) -> int:
    """Every ``COUNT`` line on stdin: put that many ISMs, the area's in turn, as fast as the
    link takes them (BLOCK)."""
    import zenoh

    from sogm_service.bench.procs import _stop_event, _transport

    p = argparse.ArgumentParser(prog="python -m sogm_service.bench.cluster_scale publish")
    p.add_argument("--connect", required=True)
    p.add_argument("--key", required=True)
    p.add_argument("--zenoh-config", type=Path, default=None)
    args = p.parse_args(argv)
    stop = _stop_event()
    data = payloads()
    session = open_session(_transport(args).client(args.connect))
    try:
        pub = session.declare_publisher(args.key,
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        print("ready", flush=True)
        n = 0
        for line in sys.stdin:
            if stop.is_set() or not line.strip():
                break
            for _ in range(int(line)):
                if stop.is_set():
                    break
                pub.put(data[n % len(data)])
                n += 1
        pub.undeclare()
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] != ["publish"]:
        sys.exit("usage: python -m sogm_service.bench.cluster_scale publish --connect EP --key K")
    sys.exit(run_publisher(sys.argv[2:]))
