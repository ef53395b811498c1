"""``sogm-service demo``: a map server and a simulated fleet on 127.0.0.1, end to end.

Everything a new user should see in their first minute: a server (in this process, with a tile
store in the output folder), robots that each open their own Zenoh session and publish ISMs and
poses like real clients, then the service queried like a client would, with pictures.

Outputs (``--out``, default ``demo-out/``): ``layer_<name>.png`` per layer, ``classes.png``
(each cell coloured by its most likely class), ``fused_bayes.png`` and ``fused_max.png``
(Eq. 6), ``submap_<robot>.png`` (a rotated window around each robot at another resolution),
``supercells.png`` (the SEVDS graph over the fused map), ``ground_truth.png``,
``tile_events.log`` (one JSON event a line), ``tiles/`` (the tile store) and ``summary.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sogm_service.apps.options import command, require_extra
from sogm_service.wire.compression import Compression


@dataclass
class DemoResult:
    """What the demo measured (also written as ``summary.json``)."""

    world: str
    robots: int
    duration_s: float
    isms_published: int
    isms_fused: int
    isms_rejected: int
    tile_switches: int
    layers: list[str]
    iou: dict[str, float]
    submap_latency_ms: dict[str, float]
    files: list[str] = field(default_factory=list)
    supercells: int | None = None
    wall_s: float = 0.0
    moving: dict[str, Any] = field(default_factory=dict)  # the forgetting person layer
    isms_dropped_offline: int = 0  # by the robots' offline policy during drop-outs
    isms_lost_in_flight: int = 0  # sent as a link went, never received (by the server's acks)
    layer_mode: str = "shared"  # or per_robot: each robot its layers, read by class patterns
    classes: dict[str, Any] = field(default_factory=dict)  # class -> its entry, its layers

    @property
    def complete(self) -> bool:
        """The server fused every ISM it was sent (all published, less those the robots'
        offline policy dropped and those lost on a link as it went)."""
        return self.isms_fused >= (self.isms_published - self.isms_dropped_offline
                                   - self.isms_lost_in_flight)


def add_parser(subparsers: Any) -> None:
    p = command(subparsers, "demo", "embedded demo: a server and a simulated fleet on 127.0.0.1",
                description="A map server and a simulated fleet on 127.0.0.1, end to end: "
                            "robots publish ISMs and poses like real clients, then the map is "
                            "queried like a client would, with pictures in --out.",
                quiet_long=False)  # --quiet is the demo's: no progress bar
    p.add_argument("--world", choices=["warehouse", "tabletop"], default="warehouse",
                   help="the simulated scene")
    p.add_argument("--tabletop", action="store_true",
                   help="the paper's table-top scene (= --world tabletop)")
    p.add_argument("--robots", type=int, default=3, metavar="N", help="robots in the fleet")
    p.add_argument("--duration", type=float, default=60.0, metavar="S",
                   help="simulated seconds")
    p.add_argument("--speed", type=float, default=3.0, metavar="X",
                   help="simulated seconds per wall second")
    p.add_argument("--rate", type=float, default=4.0, metavar="HZ",
                   help="sensor rate per robot (Hz)")
    p.add_argument("--seed", type=int, default=0, help="seed of the world and the fleet")
    p.add_argument("--out", type=Path, default=Path("demo-out"), metavar="DIR",
                   help="folder of the pictures, the tile store and summary.json")
    p.add_argument("--fast", action="store_true",
                   help="do not pace the fleet in real time (as fast as the server fuses)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--view", action="store_true",
                   help="watch the fleet map live in the browser (sogm-service view; needs the "
                        "viewer extra); after the run the map stays up until Ctrl-C")
    p.add_argument("--http", default="127.0.0.1:8080", metavar="HOST:PORT",
                   help="where --view serves its page (loopback)")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="drive the fleet and the queries into a running server instead of an "
                        "embedded one: every session of the demo opens from FILE as it is "
                        "(its map must be --map; default: none)")
    p.add_argument("--map", default="demo", help="map name")
    p.add_argument("--compression", choices=["zstd", "none"], default="zstd",
                   help="zstd: the fleet's ISMs and the demo's replies travel compressed; "
                        "none: raw (the baseline of 'sogm-service bench bandwidth')")
    p.add_argument("--secure", action="store_true",
                   help="run everything through a fresh dev PKI (DIR/pki): mutual TLS and the "
                        "access-control rules of 'sogm-service certs', one identity per robot")
    p.add_argument("--per-robot-layers", action="store_true",
                   help="every robot writes its own layers (<robot>/<sensor>/<class>, named "
                        "by the server from the key); the demo reads each class through the "
                        "pattern */*/<class>")
    p.set_defaults(handler=run)


def main(argv: list[str] | None = None) -> int:
    """sogm-service demo with these arguments."""
    from sogm_service.apps import cli

    return cli.main(["demo", *(sys.argv[1:] if argv is None else argv)])


def run(args: argparse.Namespace) -> int:
    if args.view:
        require_extra("viewer", "demo --view")
    world = "tabletop" if args.tabletop else args.world
    result = run_demo(world=world, robots=args.robots, duration_s=args.duration,
                      rate_hz=args.rate, seed=args.seed, out=args.out,
                      realtime=not args.fast, speed=args.speed, progress=not args.quiet,
                      secure=args.secure, view=args.http if args.view else None,
                      zenoh_config=args.zenoh_config, map_name=args.map,
                      compression=None if args.compression == "none" else "zstd",
                      per_robot_layers=args.per_robot_layers)
    _print_summary(result, args.out)
    return 0 if result.complete else 1


def run_demo(*, world: str = "warehouse", robots: int = 3, duration_s: float = 60.0,
             rate_hz: float = 4.0, seed: int = 0, out: Path = Path("demo-out"),
             realtime: bool = True, speed: float = 3.0, progress: bool = True,
             secure: bool = False, view: str | None = None, zenoh_config: Path | None = None,
             map_name: str = "demo", compression: Compression | None = "zstd",
             per_robot_layers: bool = False) -> DemoResult:
    """Run the whole demo; returns its summary (and writes every file into ``out``).

    ``secure``: a fresh dev PKI in ``out/pki`` (:func:`sogm_service.apps.certs.init_pki`); the
    server, each robot and the demo's own client (a viewer) open their sessions from their
    identity's config: mutual TLS and access control by certificate name, end to end.
    ``view``: serve the live viewer on that ``HOST:PORT`` during the run, and after it until
    SIGINT/SIGTERM.  ``zenoh_config``: no embedded server; the robots and the demo's client
    open their sessions from that file (as it is) and drive a running server's map
    ``map_name``.  ``compression``: the fleet's ISMs and the demo's queries (``None``: raw).
    ``per_robot_layers``: :mod:`sogm_service.apps.demo_layers`."""
    from sogm_service.apps.demo_layers import DemoLayers
    from sogm_service.apps.demo_person import PERSON_LAYER
    from sogm_service.client.mapclient import MapClient
    from sogm_service.client.session import free_tcp_endpoint
    from sogm_service.service.server.server import MapServer
    from sogm_service.sim import tabletop_world, warehouse_world

    started = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    w = tabletop_world(seed) if world == "tabletop" else warehouse_world(seed)
    endpoint = free_tcp_endpoint()
    configs: dict[str, Path] = {}
    zenoh: dict[str, Any] = {"listen": [endpoint]}
    if secure:
        configs = _dev_pki(out / "pki", endpoint, robots)
        zenoh = {"config_file": str(configs["server"])}
    from sogm_service.apps.demo_person import forgetting_config

    naming = DemoLayers(per_robot_layers)
    person = naming.entry(PERSON_LAYER)  # the forget rule, the keepout and its readers

    server: Any
    if zenoh_config is not None:  # a running server: every session from the file
        configs = {f"robot{i + 1}": zenoh_config for i in range(robots)}
        configs["viewer"] = zenoh_config
        server = _Remote(map_name, zenoh_config)
    else:
        server = MapServer(forgetting_config(_config(w.geometry.resolution, zenoh, out),
                                             w, person)).start()
    viewer = None
    try:
        if view is not None:
            viewer = _start_viewer(endpoint, view, configs.get("viewer"), map_name, person)
        with MapClient.connect(endpoint, map_name=map_name, timeout=10.0,
                               zenoh_config=configs.get("viewer")) as client:
            client.compression = compression
            watcher = _FleetWatcher(client, out / "tile_events.log")
            from sogm_service.apps.demo_person import KeepoutTimeline

            keepout = KeepoutTimeline(client, w, time.time(), person=person).start()
            fleet = _drive(w, endpoint, robots, duration_s, rate_hz, seed, realtime, speed,
                           server, progress, configs, compression, map_name, per_robot_layers)
            timeline = keepout.stop()
            if isinstance(server, _Remote):
                server.wait_idle(60.0, published=fleet.isms_sent - fleet.isms_lost)
            else:
                server.wait_idle(timeout=60.0)
            result = _report(client, server, w, watcher, fleet, world, robots, duration_s, out,
                             naming)
            if result.moving:
                result.moving["keepout_timeline"] = timeline  # (simulated s, cells, m)
            watcher.close()
        if viewer is not None:
            print(f"sogm-service demo: done; the map stays at {viewer.url} until Ctrl-C",
                  flush=True)
            _until_signal()
    finally:
        if viewer is not None:
            viewer.stop()  # its session closes before the server's
        server.stop()
    result.wall_s = round(time.monotonic() - started, 2)
    (out / "summary.json").write_text(json.dumps(result.__dict__, indent=2) + "\n")
    return result


class _Remote:
    """A running server the demo did not start (``demo --zenoh-config``): its counters and
    "idle" through a client of its own, nothing to stop."""

    def __init__(self, map_name: str, zenoh_config: Path) -> None:
        from sogm_service.client.mapclient import MapClient

        self._client = MapClient.connect(map_name=map_name, zenoh_config=zenoh_config,
                                         timeout=10.0)
        self.stats = self

    def snapshot(self) -> tuple[dict[str, int], dict[str, int]]:
        reply = self._client.stats()
        return dict(reply.counters), dict(reply.rejected)

    def wait_idle(self, timeout: float, published: int = 0) -> bool:
        """Until the server handled at least as many ISMs as the fleet published."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            counters, _ = self.snapshot()
            if counters.get("isms_fused", 0) + counters.get("isms_rejected", 0) >= published:
                return True
            time.sleep(0.1)
        return False

    def stop(self) -> None:
        self._client.close()


def _start_viewer(endpoint: str, http: str, zenoh_config: Path | None,
                  map_name: str, person: str) -> Any:
    from sogm_service.apps.viewer import start_viewer

    args = ["--connect", endpoint, "--map", map_name, "--http", http,
            "--keepout", person]  # the view 'keepout mask' follows the person
    if zenoh_config is not None:
        args += ["--zenoh-config", str(zenoh_config)]
    viewer = start_viewer(args)
    print(f"sogm-service demo: watch the fleet at {viewer.url}", flush=True)
    return viewer


def _until_signal() -> None:
    import signal

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(0.5):
        pass


def _dev_pki(directory: Path, endpoint: str, robots: int) -> dict[str, Path]:
    """A fresh PKI for the demo: the server listens on ``endpoint`` over TLS; the configs of the
    server, the viewer and each robot by name."""
    from sogm_service.apps.certs import init_pki

    names = [f"robot{i + 1}" for i in range(robots)]  # the fleet's names (sim/fleet.py)
    pki = init_pki(directory, server_names=["server"], robot_names=names,
                   viewer_names=["viewer"], endpoint=endpoint.replace("tcp/", "tls/", 1),
                   map_name="demo", force=True)
    return {name: pki.config(name) for name in ["server", "viewer", *names]}


def _config(resolution: float, zenoh: dict[str, Any], out: Path) -> Any:
    from sogm_service.service.config import ServiceConfig

    return ServiceConfig.model_validate({
        "map": {"name": "demo", "resolution": resolution},
        "storage": {"directory": str(out / "tiles"), "checkpoint_interval_s": 2.0},
        "tiles": {"hysteresis_m": min(1.0, 64 * resolution)},
        "zenoh": zenoh,
        "log_level": "warning",
    })


class _FleetWatcher:
    """Follows robot poses and tile events like any other client of the service."""

    def __init__(self, client: Any, events_path: Path) -> None:
        from sogm_service.wire import codec
        from sogm_service.wire.messages import PoseMessage

        self.poses: dict[str, PoseMessage] = {}
        self.events = 0
        self._log = events_path.open("w", encoding="utf-8")
        self._lock = threading.Lock()

        def on_pose(sample: Any) -> None:
            msg = codec.decode(PoseMessage, sample.payload.to_bytes())
            with self._lock:
                self.poses[str(sample.key_expr).rsplit("/", 1)[-1]] = msg

        self._subs = [client.session.declare_subscriber("pose/**", on_pose),
                      client.subscribe_tile_events(self._on_event)]

    def _on_event(self, event: Any) -> None:
        with self._lock:
            self.events += 1
            self._log.write(event.model_dump_json() + "\n")

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._log.close()


def _drive(world: Any, endpoint: str, robots: int, duration_s: float, rate_hz: float,
           seed: int, realtime: bool, speed: float, server: Any, progress: bool,
           configs: dict[str, Path], compression: Compression | None = "zstd",
           map_name: str = "demo", per_robot_layers: bool = False) -> Any:
    """Run the fleet in a thread while a progress bar shows the server's view."""
    from sogm_service.sim.fleet import run_fleet

    box: dict[str, Any] = {}

    def fleet() -> None:
        from sogm_service.apps.demo_person import demo_observers, demo_sensors

        box["stats"] = run_fleet(world, endpoint, robots=robots, duration_s=duration_s,
                                 rate_hz=rate_hz, seed=seed, realtime=realtime, speed=speed,
                                 zenoh_configs=configs or None,
                                 sensors=demo_sensors(world),
                                 observers=demo_observers(world),
                                 compression=compression, map_name=map_name,
                                 per_robot_layers=per_robot_layers)

    thread = threading.Thread(target=fleet, name="demo-fleet")
    t0 = time.monotonic()
    wall = duration_s / speed if realtime else None
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    # A bar with the time left on a terminal; a line every 5 s in a log.
    bar = tqdm(total=round(wall, 1) if wall else None, unit="s", desc="demo", file=sys.stderr,
               disable=not progress, mininterval=0.25 if tty else 5.0, dynamic_ncols=True,
               bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}]"
                          "{postfix}" if wall else None)
    thread.start()
    while thread.is_alive():
        thread.join(0.25)
        elapsed = time.monotonic() - t0
        fused = server.stats.snapshot()[0].get("isms_fused", 0)
        bar.set_postfix_str(f"ISMs fused: {fused}", refresh=False)
        bar.update(min(elapsed, wall or elapsed) - bar.n)
    bar.close()
    if "stats" not in box:
        raise RuntimeError("the simulated fleet failed; see the log above")
    return box["stats"]


def _report(client: Any, server: Any, world: Any, watcher: _FleetWatcher, fleet: Any,
            world_name: str, robots: int, duration_s: float, out: Path,
            naming: Any) -> DemoResult:
    from sogm_service.apps.demo_layers import label
    from sogm_service.apps.demo_person import MOVING_LAYERS, PERSON_LAYER, report_moving
    from sogm_service.apps.demo_pictures import (
        class_iou,
        ground_truth_image,
        obstacle_layers,
        robot_markers,
        robot_submaps,
        world_window,
        write_fused,
        write_layers,
        write_supercells,
    )

    files: list[str] = []
    info = client.info()
    moving = report_moving(client, world, out, files, duration_s, naming.entry(PERSON_LAYER))
    layers = naming.entries(info.layers, skip=MOVING_LAYERS)  # the person: on its own
    full = world_window(world)
    sub = client.submap(**full, layers=layers, encoding="prob_f32")
    markers = robot_markers(watcher)
    files += write_layers(sub, out, markers)
    files += write_fused(client, full, obstacle_layers(layers), out, markers)
    from sogm_service.apps.render import class_legend, save_map_png

    save_map_png(out / "ground_truth.png", ground_truth_image(world, layers), world.geometry,
                 title="ground truth (the simulator's world)",
                 legend=class_legend([label(n) for n in layers]),
                 robots=markers)
    files.append("ground_truth.png")
    latency = robot_submaps(client, watcher, world.geometry.resolution, out, files, layers)
    supercells = write_supercells(client, world, watcher, out, files, layers)
    counters, rejected = server.stats.snapshot()
    return DemoResult(
        world=world_name, robots=robots, duration_s=duration_s, isms_published=fleet.isms,
        isms_fused=counters.get("isms_fused", 0), isms_rejected=sum(rejected.values()),
        tile_switches=watcher.events, layers=layers,
        iou=class_iou(world, layers, sub.probabilities()), submap_latency_ms=latency,
        files=sorted(files), supercells=supercells, moving=moving,
        isms_dropped_offline=fleet.isms_dropped, isms_lost_in_flight=fleet.isms_lost,
        layer_mode=naming.mode, classes=naming.summary(
            layers + ([moving["layer"]] if moving else []), client.info().layers))


def _print_summary(r: DemoResult, out: Path) -> None:
    print(f"sogm-service demo: {r.world}, {r.robots} robots, {r.duration_s:.0f} s simulated, "
          f"{r.wall_s:.1f} s wall")
    print(f"  ISMs published {r.isms_published}, fused {r.isms_fused}, "
          f"rejected {r.isms_rejected}; tile switches {r.tile_switches}")
    if r.isms_dropped_offline or r.isms_lost_in_flight:
        print(f"  drop-outs: {r.isms_dropped_offline} ISMs dropped by the offline policy "
              f"(the latest per layer kept or sent again), {r.isms_lost_in_flight} lost in "
              "flight (no copy left to send again)")
    if not r.complete:
        print(f"  incomplete: the server fused {r.isms_fused} of the "
              f"{r.isms_published - r.isms_dropped_offline - r.isms_lost_in_flight} "
              "ISMs it was sent")
    if r.layer_mode == "per_robot":
        print("  per-robot layers, read by class: " + ", ".join(
            f"{c['entry']} ({len(c['members'])} layers)" for c in r.classes.values()))
    print("  per-class IoU (observed cells): " +
          ", ".join(f"{k} {v:.2f}" for k, v in r.iou.items()))
    if r.submap_latency_ms:
        print(f"  sub-map query latency: median {r.submap_latency_ms['p50']:.1f} ms, "
              f"p99 {r.submap_latency_ms['p99']:.1f} ms")
    if r.supercells is not None:
        print(f"  supercells in the graph window: {r.supercells}")
    if r.moving:
        m = r.moving
        age = m.get("oldest_occupied_age_s")
        print(f"  moving person (layer {m['layer']}, half-life {m['half_life_s']:.0f} s): "
              f"{m['occupied_cells']} cells occupied now"
              + (f", last walked {age:.0f} s ago at most" if age is not None else "")
              + f"; highest p {m['p_max_now']:.2f}")
        k_age = m.get("keepout_oldest_age_s")
        print(f"  nav2 keepout of the person: {m['keepout_cells']} cells now"
              + (f", where it walked {k_age:.0f} s ago at most (older spots faded)"
                 if k_age is not None else ""))
        seen = [(t, n, d) for t, n, d in m.get("keepout_timeline", []) if n]
        if seen:
            far = max(d for _, _, d in seen if d is not None)
            print(f"    kept out from {seen[0][0]:.0f} s to {seen[-1][0]:.0f} s (simulated), "
                  f"at most {max(n for _, n, _ in seen)} cells, their centre within "
                  f"{far:.1f} m of the person")
    print(f"  wrote {len(r.files)} files and summary.json to {out}/")
