"""Helper processes of the Zenoh benchmarks: ``python -m sogm_service.bench.procs ROLE ...``.

Each role opens its own session (never forked from a process that has one), installs its
signal handlers before opening it, and closes it on SIGTERM or end of stdin.

* ``queryable``: replies to every get on ``--key`` with one prepared payload of ``--size`` bytes
  (the raw baseline of the submap benchmark).
* ``counter``: a subscriber that only counts; prints ``done <t_first> <t_last>`` (wall clock)
  every ``--count`` samples (the raw baseline of the ingestion benchmark).
* ``publisher``: for every ``go`` line on stdin puts the ``--count`` ISM payloads (prepared
  before timing, congestion control BLOCK) and prints ``sent <t_first> <t_last>``.
* ``flood``: for every ``SECONDS`` line on stdin puts ISMs as fast as the link takes them
  (``--robots`` keys in turn, BLOCK) for that long and prints ``sent <count> <t_first>
  <t_last>``.
* ``paced``: a fleet at a steady rate: for every ``RATE SECONDS`` line on stdin puts ISMs at
  ``RATE`` per second for ``SECONDS`` (``--robots`` x 4 keys in turn, BLOCK) and prints
  ``sent <count> <t_first> <t_last>``; ``--layers`` names the layers every robot writes,
  ``--per-robot`` gives each robot its own (``ism/robot<r>/layer<l>``).
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from sogm_service.bench.transport import Transport
from sogm_service.client.session import open_session
from sogm_service.wire import codec


def _transport(args: argparse.Namespace) -> Transport:
    """This role's side of the bench's transport: its ``--zenoh-config`` (or plain TCP)."""
    config = args.zenoh_config
    return Transport(client_config=config, server_config=config)


def _stop_event() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _say(text: str) -> None:
    print(text, flush=True)


def run_queryable(args: argparse.Namespace, stop: threading.Event) -> None:
    payload = bytes(args.size)
    session = open_session(_transport(args).server(args.listen))
    try:
        q = session.declare_queryable(args.key, lambda query: query.reply(query.key_expr,
                                                                          payload))
        _say("ready")
        stop.wait()
        q.undeclare()
    finally:
        session.close()


def run_counter(args: argparse.Namespace, stop: threading.Event) -> None:
    state = {"n": 0, "first": 0.0}

    def on_sample(sample: zenoh.Sample) -> None:
        now = time.time()
        if state["n"] == 0:
            state["first"] = now
        state["n"] += 1
        if state["n"] == args.count:
            _say(f"done {state['first']:.6f} {now:.6f}")
            state["n"] = 0

    session = open_session(_transport(args).server(args.listen))
    try:
        sub = session.declare_subscriber(args.key, on_sample)
        _say("ready")
        stop.wait()
        sub.undeclare()
    finally:
        session.close()


def ism_payloads(count: int, size: int, seed: int = 0,
                 layers: list[str] | None = None) -> list[bytes]:
    """``count`` encoded 256x256-class ISMs at robot-like poses (any heading) in a 20 m area;
    with ``layers``, ISM k names layer ``layers[k % len(layers)]`` (else its key decides)."""
    import numpy as np

    from sogm_service.bench.compute import MAP_RES, ism_message, synthetic_ism
    from sogm_service.core.geometry import Pose2D

    rng = np.random.default_rng(seed)
    codes = [synthetic_ism(size, s) for s in range(4)]
    out = []
    for k in range(count):
        x, y = rng.uniform(0.0, 20.0, 2)
        yaw = float(rng.uniform(-math.pi, math.pi))
        msg = ism_message(codes[k % 4], MAP_RES, Pose2D(x, y, yaw))
        if layers:
            msg = msg.model_copy(update={"layer": layers[k % len(layers)]})
        out.append(codec.encode(msg))
    return out


def run_publisher(args: argparse.Namespace, stop: threading.Event) -> None:
    payloads = ism_payloads(args.count, args.size)
    session = open_session(_transport(args).client(args.connect))
    try:
        pub = session.declare_publisher(args.key,
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        _say("ready")
        for line in sys.stdin:
            if stop.is_set() or line.strip() != "go":
                break
            t0 = time.time()
            for p in payloads:
                pub.put(p)
            _say(f"sent {t0:.6f} {time.time():.6f}")
        pub.undeclare()
    finally:
        session.close()


def run_paced(args: argparse.Namespace, stop: threading.Event) -> None:
    # The fleet writes the layers the bench's client reads (--layers): the contention a query
    # meets when robots map what it asks for; without, each key is its own layer.
    # --per-robot: every robot its own layers, named by the key (ism/robot<r>/layer<l>).
    payloads = ism_payloads(64, args.size, layers=args.layers.split(",") if args.layers else None)
    # Under access control one identity puts under its own name only: ism/<owner>/robot<r>/...
    leaf = "layer" if args.per_robot else "sensor/class"
    keys = [f"ism/{args.owner}/robot{r}/{leaf}{c}" if args.owner else
            f"ism/robot{r}/{leaf}{c}" for r in range(args.robots) for c in range(4)]
    session = open_session(_transport(args).client(args.connect))
    try:
        pubs = [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                for k in keys]
        _say("ready")
        for line in sys.stdin:
            if stop.is_set() or not line.strip():
                break
            rate, seconds = (float(v) for v in line.split())
            n = int(rate * seconds)
            t0 = time.time()
            for k in range(n):  # ISM k is due at t0 + k / rate: a steady fleet, no bursts
                delay = t0 + k / rate - time.time()
                if delay > 0:
                    time.sleep(delay)
                pubs[k % len(pubs)].put(payloads[k % len(payloads)])
            _say(f"sent {n} {t0:.6f} {time.time():.6f}")
        for pub in pubs:
            pub.undeclare()
    finally:
        session.close()


def run_flood(args: argparse.Namespace, stop: threading.Event) -> None:
    """Every ``SECONDS`` line on stdin: put ISMs as fast as the link takes them (BLOCK) for
    that long, ``--robots`` keys in turn, then print ``sent <count> <t_first> <t_last>``."""
    layers = args.layers.split(",") if args.layers else None
    payloads = ism_payloads(64, args.size, seed=args.seed, layers=layers)
    keys = [f"ism/{args.owner}/flood{args.seed}/robot{r}" if args.owner else
            f"ism/flood{args.seed}/robot{r}/obstacle" for r in range(args.robots)]
    session = open_session(_transport(args).client(args.connect))
    try:
        pubs = [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                for k in keys]
        _say("ready")
        for line in sys.stdin:
            if stop.is_set() or not line.strip():
                break
            t0 = time.time()
            t_end, n = t0 + float(line), 0
            while time.time() < t_end and not stop.is_set():
                pubs[n % len(pubs)].put(payloads[n % len(payloads)])
                n += 1
            _say(f"sent {n} {t0:.6f} {time.time():.6f}")
        for pub in pubs:
            pub.undeclare()
    finally:
        session.close()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m sogm_service.bench.procs")
    sub = p.add_subparsers(dest="role", required=True)
    q = sub.add_parser("queryable")
    q.add_argument("--listen", required=True)
    q.add_argument("--key", required=True)
    q.add_argument("--size", type=int, required=True)
    c = sub.add_parser("counter")
    c.add_argument("--listen", required=True)
    c.add_argument("--key", required=True)
    c.add_argument("--count", type=int, required=True)
    pb = sub.add_parser("publisher")
    pb.add_argument("--connect", required=True)
    pb.add_argument("--key", required=True)
    pb.add_argument("--count", type=int, required=True)
    pb.add_argument("--size", type=int, default=256)
    pc = sub.add_parser("paced")
    pc.add_argument("--connect", required=True)
    pc.add_argument("--robots", type=int, default=8)
    pc.add_argument("--size", type=int, default=256)
    pc.add_argument("--owner", default=None, help="the robot identity every key is under")
    pc.add_argument("--layers", default=None, help="comma-separated layers the ISMs name")
    pc.add_argument("--per-robot", action="store_true",
                    help="keys ism/robot<r>/layer<l>: each robot writes its own 4 layers")
    fl = sub.add_parser("flood")
    fl.add_argument("--connect", required=True)
    fl.add_argument("--robots", type=int, default=8)
    fl.add_argument("--size", type=int, default=128)
    fl.add_argument("--seed", type=int, default=0, help="this publisher's number (its keys)")
    fl.add_argument("--owner", default=None, help="the robot identity every key is under")
    fl.add_argument("--layers", default=None, help="comma-separated layers the ISMs name")
    for role in (q, c, pb, pc, fl):
        role.add_argument("--zenoh-config", type=Path, default=None,
                          help="open the session from this Zenoh config (endpoints replaced)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    stop = _stop_event()  # before any session: an early SIGTERM still closes cleanly
    roles: dict[str, Any] = {"queryable": run_queryable, "counter": run_counter,
                             "publisher": run_publisher, "paced": run_paced,
                             "flood": run_flood}
    roles[args.role](args, stop)
    return 0


if __name__ == "__main__":
    sys.exit(main())
