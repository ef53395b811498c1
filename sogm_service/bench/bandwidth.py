"""``bandwidth``: the bytes the embedded demo fleet puts on the network, compressed vs raw.

One run per mode, each against a fresh ``sogm-service serve --ros2`` (without ``--ros2`` when
the ros2 extra is missing, and the row says so) on an ephemeral loopback port, every session
with Zenoh shared memory off (on one host Zenoh would otherwise carry large payloads through
shared memory and the network cost would not show):

* the fleet: ``sogm-service demo --zenoh-config FILE --map default --compression MODE`` in its
  own process, every session of it connected through a TCP relay of this process that counts
  the bytes each way (the Zenoh frames as they would cross a link: ISMs, poses, queries,
  replies, declarations);
* a ROS 2 tool: a plain session subscribed to ``**`` straight to the server, counting each
  sample's payload by class (the ISMs' layer, poses, the ROS 2 grids and their updates).  The
  ROS 2 maps cross the network only because someone subscribes to them: this is that someone.

Classes: ``ism_<layer>`` (payloads, robot to server), ``poses``, ``ros2_*`` (payloads, server
to the tool), ``queries_replies`` (the fleet's downlink but the poses its watcher follows) and
``other`` (the fleet's uplink but its ISMs and poses: framing, declarations, query bodies).
The network total is the relay's two directions plus the ROS 2 payloads.  Bytes per robot per
second are per simulated second: a real robot at the demo's sensor rate.

The ratio is now / raw (the raw run differs only in compression: its ROS 2 maps are the same
rectangles of what changed).  The ROS 2 share compares the ROS 2 payloads with what sending
every changed grid whole at each publication would have cost (the server's
``whole_equivalent_bytes`` counter).  The target of the full run (60 s simulated): at most
50 MB on the network, every ISM fused in both runs and the same per-class IoU; ``--quick``
(10 s) only reports, since the whole grids a ROS 2 tool gets first weigh more in a short run.
"""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import zenoh

from sogm_service.bench.core import Details, Row
from sogm_service.bench.zbench import PY, Proc
from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint, wait_listening

ROBOTS = 3
SPEED = 3.0
BUDGET_MB = 50.0
"""The full run's budget (60 s simulated): the network total, every class included."""
ROS2_UPDATE_TYPE = "OccupancyGridUpdate"


def zenoh_json5(path: Path, mode: str, *, listen: str | list[str] | None = None,
                connect: str | None = None) -> Path:
    """A Zenoh config file: ``mode``, the endpoints, multicast scouting and shared memory off."""
    config: dict[str, Any] = {"mode": mode, "scouting": {"multicast": {"enabled": False}},
                              "transport": {"shared_memory": {"enabled": False}}}
    if listen:
        config["listen"] = {"endpoints": [listen] if isinstance(listen, str) else listen}
    if connect:
        config["connect"] = {"endpoints": [connect]}
    path.write_text(json.dumps(config, indent=2) + "\n", encoding="utf-8")
    return path


def key_class(key: str) -> str:
    """The traffic class of a sample's key: ``ism_<layer>``, ``poses``, ``ros2_<what>``,
    ``sogm`` (the service's own events) or ``other``."""
    parts = key.split("/")
    if parts[0] == "ism":
        return f"ism_{parts[-1]}"
    if parts[0] == "pose":
        return "poses"
    if parts[0].isdigit():  # rmw_zenoh: <domain>/<topic...>/<type>/<type hash>
        what = "layer" if "/layers/" in key else "map"
        return f"ros2_{what}_{'updates' if ROS2_UPDATE_TYPE in key else 'grids'}"
    if parts[0] == "sogm":
        return "sogm"
    return "other"


class Tally:
    """Samples and payload bytes per class, counted from a subscriber's callback."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.samples: dict[str, int] = defaultdict(int)
        self.bytes: dict[str, int] = defaultdict(int)

    def add(self, key: str, size: int) -> None:
        cls = key_class(key)
        with self._lock:
            self.samples[cls] += 1
            self.bytes[cls] += size

    def snapshot(self) -> tuple[dict[str, int], dict[str, int]]:
        with self._lock:
            return dict(self.samples), dict(self.bytes)


@contextmanager
def counting_subscriber(config: Path) -> Iterator[Tally]:
    """A session of its own from ``config`` subscribed to ``**``, counting every sample."""
    tally = Tally()
    session = zenoh.open(zenoh.Config.from_file(str(config)))
    try:
        sub = session.declare_subscriber(
            "**", lambda s: tally.add(str(s.key_expr), len(s.payload)))
        try:
            yield tally
        finally:
            sub.undeclare()
    finally:
        session.close()


class Relay:
    """A TCP relay on 127.0.0.1 to ``target`` (``tcp/host:port``) that counts bytes each way:
    ``up`` (towards the target) and ``down``."""

    def __init__(self, target: str) -> None:
        host, port = target.split("/", 1)[1].rsplit(":", 1)
        self._target = (host, int(port))
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = f"tcp/127.0.0.1:{self._listener.getsockname()[1]}"
        self._lock = threading.Lock()
        self.up = 0
        self.down = 0
        self._socks: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._stopped = False
        self._accepter = threading.Thread(target=self._accept, name="bench-relay", daemon=True)
        self._accepter.start()

    def counts(self) -> tuple[int, int]:
        with self._lock:
            return self.up, self.down

    def _accept(self) -> None:
        while not self._stopped:
            try:
                inner, _ = self._listener.accept()
            except OSError:
                return
            try:
                outer = socket.create_connection(self._target, timeout=10.0)
                outer.settimeout(None)
            except OSError:
                inner.close()
                continue
            for s in (inner, outer):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._socks += [inner, outer]
            for src, dst, up in ((inner, outer, True), (outer, inner, False)):
                t = threading.Thread(target=self._pump, args=(src, dst, up), daemon=True)
                self._threads.append(t)
                t.start()

    def _pump(self, src: socket.socket, dst: socket.socket, up: bool) -> None:
        try:
            while True:
                data = src.recv(1 << 16)
                if not data:
                    break
                dst.sendall(data)
                with self._lock:
                    if up:
                        self.up += len(data)
                    else:
                        self.down += len(data)
        except OSError:
            pass
        finally:
            with suppress(OSError):
                dst.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        self._stopped = True
        self._listener.close()
        with self._lock:
            socks = list(self._socks)
        for s in socks:
            s.close()
        for t in self._threads:
            t.join(5.0)


def ros2_available() -> bool:
    return importlib.util.find_spec("rosbags") is not None


@contextmanager
def serve(directory: Path, ros2: bool, listen: list[str] | None = None) -> Iterator[str]:
    """``sogm-service serve [--ros2]`` with shared memory off on an ephemeral loopback port (or
    on ``listen``), once it answers; yields its loopback endpoint (else its first)."""
    endpoints = listen or [free_tcp_endpoint()]
    endpoint = next((e for e in endpoints if e.startswith("tcp/127.0.0.1:")), endpoints[0])
    config = zenoh_json5(directory / "server.json5", "peer", listen=endpoints)
    proc = Proc([PY, "-m", "sogm_service", "serve", "--zenoh-config", str(config),
                 *(["--ros2"] if ros2 else [])], directory / "server.log")
    try:
        wait_listening(endpoint, 30.0, lambda: proc.popen.poll() is not None, proc.tail)
        with MapClient.connect(zenoh_config=zenoh_json5(directory / "probe.json5", "client",
                                                        connect=endpoint),
                               timeout=10.0) as client:
            deadline = time.monotonic() + 30.0
            while not client.servers(timeout=1.0):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"server not discoverable:\n{proc.tail()}")
        yield endpoint
    finally:
        proc.stop()


def demo_command(config: Path, out: Path, duration: float, compression: str) -> list[str]:
    """The demo fleet driven into a running server's map ``default`` (every session from
    ``config``)."""
    return [PY, "-m", "sogm_service", "demo", "--zenoh-config", str(config), "--map", "default",
            "--duration", f"{duration:g}", "--speed", f"{SPEED:g}", "--robots", str(ROBOTS),
            "--out", str(out), "--quiet", "--compression", compression]


def run_mode(directory: Path, compression: str, duration: float, ros2: bool) -> dict[str, Any]:
    """One demo run against a fresh server: bytes by class, the demo's summary, wall time."""
    import subprocess

    d = directory / compression
    d.mkdir(parents=True, exist_ok=True)
    with serve(d, ros2) as endpoint:
        relay = Relay(endpoint)
        try:
            sub_config = zenoh_json5(d / "counter.json5", "client", connect=endpoint)
            with counting_subscriber(sub_config) as tally:
                time.sleep(0.5)  # the subscription reaches the server before the fleet starts
                t0 = time.monotonic()
                fleet = zenoh_json5(d / "fleet.json5", "client", connect=relay.endpoint)
                with open(d / "demo.log", "wb") as log:
                    proc = subprocess.run(demo_command(fleet, d / "out", duration, compression),
                                          stdout=log, stderr=subprocess.STDOUT,
                                          timeout=duration / SPEED * 10 + 120)
                wall = time.monotonic() - t0
                if proc.returncode != 0:
                    raise RuntimeError(f"the demo failed ({proc.returncode}): "
                                       f"{(d / 'demo.log').read_text()[-1500:]}")
                time.sleep(0.5)  # the last ROS 2 publication reaches the counter
                samples, payload = tally.snapshot()
                ros2_counters = _ros2_counters(d, endpoint) if ros2 else {}
        finally:
            relay.close()
        up, down = relay.counts()
    summary = json.loads((d / "out" / "summary.json").read_text())
    return {"samples": samples, "payload": payload, "up": up, "down": down, "wall_s": wall,
            "summary": summary, "ros2": ros2_counters}


def _ros2_counters(directory: Path, endpoint: str) -> dict[str, int]:
    """The server's ROS 2 counters: what it published, and ``whole_equivalent_bytes`` (what
    republishing each changed grid whole would have sent)."""
    with MapClient.connect(zenoh_config=zenoh_json5(directory / "stats.json5", "client",
                                                    connect=endpoint),
                           timeout=10.0) as client:
        extra = client.stats().extra.get("ros2", {})
    return {k: int(v) for k, v in extra.get("counters", {}).items()}


def classes(run: dict[str, Any]) -> dict[str, int]:
    """Bytes by class of one run (see the module's docstring); ``total`` is the network's."""
    payload: dict[str, int] = run["payload"]
    isms = {k: v for k, v in payload.items() if k.startswith("ism_")}
    ros2 = {k: v for k, v in payload.items() if k.startswith("ros2_")}
    poses = payload.get("poses", 0)
    out = {**isms, **ros2, "poses": poses,
           "queries_replies": max(0, run["down"] - poses),
           "other": max(0, run["up"] - sum(isms.values()) - poses)}
    out["total"] = run["up"] + run["down"] + sum(ros2.values())
    return out


def late_joiner(directory: Path) -> Details:
    """A late joiner's mirror of a 100 m x 100 m map brought current from empty: seconds and
    bytes pulled (through the relay), when the client has ``MapClient.mirror``."""
    if not hasattr(MapClient, "mirror"):
        return {"mirror": "not available: MapClient.mirror is not in this version"}
    import numpy as np

    from sogm_service.core.geometry import Pose2D

    d = directory / "mirror"
    d.mkdir(parents=True, exist_ok=True)
    side, cells, res = 100.0, 250, 0.05  # 8 x 8 ISMs of 12.5 m cover the map
    rng = np.random.default_rng(0)
    with serve(d, ros2=False) as endpoint:
        with MapClient.connect(zenoh_config=zenoh_json5(d / "filler.json5", "client",
                                                        connect=endpoint),
                               timeout=30.0) as filler:
            n = round(side / (cells * res))
            for i in range(n):
                for j in range(n):
                    grid = rng.integers(0, 101, (cells, cells)).astype(np.int8)
                    filler.publish_ism("ism/filler/laser/obstacle", grid, resolution=res,
                                       origin=Pose2D(i * cells * res, j * cells * res, 0.0))
            filler.wait_fused(timeout=120.0)
        relay = Relay(endpoint)
        try:
            with MapClient.connect(zenoh_config=zenoh_json5(d / "joiner.json5", "client",
                                                            connect=relay.endpoint),
                                   timeout=30.0) as joiner:
                before = sum(relay.counts())
                t0 = time.perf_counter()
                mirror = joiner.mirror(side / 2, side / 2, side, side)  # centre, size
                tiles = len(mirror.refresh())
                seconds = time.perf_counter() - t0
                pulled = sum(relay.counts()) - before
                payload = mirror.last.bytes
                mirror.refresh()  # current already: only the held versions go out
                again = sum(relay.counts()) - before - pulled
        finally:
            relay.close()
    return {"mirror_s": seconds, "mirror_bytes": float(pulled), "mirror_side_m": side,
            "mirror_tiles": float(tiles), "mirror_payload_bytes": float(payload),
            "mirror_again_bytes": float(again)}


def bandwidth(quick: bool) -> Row:
    duration = 10.0 if quick else 60.0
    ros2 = ros2_available()
    load = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="sogm-bench-bw-") as tmp:
        d = Path(tmp)
        runs = {mode: run_mode(d, mode, duration, ros2) for mode in ("none", "zstd")}
        joiner = late_joiner(d)
    return _row(runs, duration, ros2, load, joiner)


def _row(runs: dict[str, dict[str, Any]], duration: float, ros2: bool,
         load: tuple[float, float, float], joiner: Details) -> Row:
    per = float(ROBOTS) * duration
    raw, now = classes(runs["none"]), classes(runs["zstd"])
    details: Details = {"duration_s": duration, "speed": SPEED, "robots": float(ROBOTS),
                        "ros2": "on" if ros2 else "off", "load_1m": load[0], **joiner}
    for mode, by in (("raw", raw), ("now", now)):
        run = runs["none" if mode == "raw" else "zstd"]
        for cls, n in by.items():
            details[f"{mode}_{cls}_bytes"] = float(n)
            details[f"{mode}_{cls}_bytes_per_robot_s"] = n / per
        for cls, n in run["samples"].items():
            details[f"{mode}_{cls}_samples"] = float(n)
        s = run["summary"]
        details.update({f"{mode}_isms_published": float(s["isms_published"]),
                        f"{mode}_isms_fused": float(s["isms_fused"]),
                        f"{mode}_wall_s": run["wall_s"],
                        f"{mode}_iou": json.dumps(s["iou"], sort_keys=True)})
    for cls in sorted(set(raw) | set(now)):
        if raw.get(cls):
            details[f"ratio_{cls}"] = now.get(cls, 0) / raw[cls]
    ratio = now["total"] / raw["total"]
    ros2_bytes = sum(n for c, n in now.items() if c.startswith("ros2_"))
    whole = runs["zstd"]["ros2"].get("whole_equivalent_bytes", 0)
    ros2_share = ros2_bytes / whole if whole else None
    if ros2_share is not None:
        details.update({"now_ros2_bytes": float(ros2_bytes),
                        "now_ros2_whole_equivalent_bytes": float(whole),
                        "ros2_share_of_whole": ros2_share})
    summaries = [r["summary"] for r in runs.values()]
    fused = all(s["isms_published"] == s["isms_fused"] for s in summaries)
    same_iou = summaries[0]["iou"] == summaries[1]["iou"]
    top = sorted(((n, c) for c, n in now.items() if c != "total"), reverse=True)[:3]
    note = (f"{duration:g} s simulated at {SPEED:g}x, {ROBOTS} robots; now "
            f"{now['total'] / 1e6:.1f} MB vs raw {raw['total'] / 1e6:.1f} MB; ISMs fused "
            f"{summaries[1]['isms_fused']}/{summaries[1]['isms_published']} (raw "
            f"{summaries[0]['isms_fused']}/{summaries[0]['isms_published']}); IoU "
            f"{'unchanged' if same_iou else 'CHANGED'}; largest now: "
            + ", ".join(f"{c} {n / per / 1e3:.1f} kB/robot/s" for n, c in top)
            + ("" if ros2 else "; serve without --ros2 (the ros2 extra is not installed)")
            + (f"; ROS 2 {ros2_bytes / 1e6:.1f} MB, {ros2_share:.1%} of republishing each "
               f"changed grid whole ({whole / 1e6:.0f} MB)" if ros2_share is not None else "")
            + (f"; late joiner's mirror of {joiner['mirror_side_m']:g} m x "
               f"{joiner['mirror_side_m']:g} m: {joiner['mirror_tiles']:g} tiles in "
               f"{joiner['mirror_s']:.2f} s, {float(joiner['mirror_bytes']) / 1e6:.1f} MB"
               if "mirror_s" in joiner else f"; {joiner.get('mirror', '')}")
            + f"; load {load[0]:.2f}")
    judged = duration >= 60.0
    passed = now["total"] <= BUDGET_MB * 1e6 and fused and same_iou
    return Row("bandwidth", now["total"] / per / 1e3, raw["total"] / per / 1e3, "kB/robot/s",
               ratio, f"<= {BUDGET_MB:g} MB per 60 s run, every ISM fused, IoU unchanged",
               passed if judged else None,
               "the same demo run with raw ISMs and replies", note, details)
