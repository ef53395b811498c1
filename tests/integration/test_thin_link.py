"""The demo fleet behind a 20 Mbit/s link: every ISM fused, queries answered, few bytes.

The fleet (``sogm-service demo --zenoh-config FILE --map default``, compressed as by default)
runs in a network namespace of its own; the server listens on the host's end of a veth pair
shaped to 20 Mbit/s both ways; every session has Zenoh shared memory off.  The bytes that
crossed the link are the host end's counters (Ethernet frames, both directions).

The bound: what the same ISMs would weigh raw, counted on the server's side of the link by a
subscriber on loopback (each ISM's cells at their encoding's size, as the raw run sends them).
The raw run puts at least that on the link (its replies add more), so a link carrying less than
a fifth of it carries less than a fifth of a raw run's.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zenoh

from sogm_service.bench.bandwidth import serve, zenoh_json5
from sogm_service.wire import codec
from sogm_service.wire.messages import IsmMessage
from tests import netns

pytestmark = [pytest.mark.integration, pytest.mark.slow]

DURATION_S = 15.0
SPEED = 3.0


class RawIsmBytes:
    """Counts the ISMs the server receives and what each would weigh uncompressed."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.isms = 0
        self.raw = 0
        self.sent = 0

    def __call__(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        msg = codec.decode(IsmMessage, payload)  # validated, its data expanded
        sent_data = msgpack.unpackb(payload)["data"]  # the data as it travelled
        with self.lock:
            self.isms += 1
            self.sent += len(payload)
            self.raw += len(payload) - len(sent_data) + len(msg.data)


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        port: int = s.getsockname()[1]
        return port


def test_demo_fleet_through_a_20_mbit_link(tmp_path: Path) -> None:
    why = netns.unavailable()
    if why is not None:
        pytest.skip(f"no shaped link: {why}")
    with netns.shaped_namespace("tl") as link:
        on_link = f"tcp/{link.host_ip}:{_free_port(link.host_ip)}"
        local = f"tcp/127.0.0.1:{_free_port('127.0.0.1')}"
        raw = RawIsmBytes()
        with serve(tmp_path, ros2=False, listen=[on_link, local]) as endpoint:
            assert endpoint == local
            watcher = zenoh.open(zenoh.Config.from_file(str(
                zenoh_json5(tmp_path / "watcher.json5", "client", connect=local))))
            try:
                sub = watcher.declare_subscriber("ism/**", raw)
                fleet = zenoh_json5(tmp_path / "fleet.json5", "client", connect=on_link)
                rx0, tx0 = link.host_bytes()
                proc = subprocess.run(
                    [*link.exec_prefix(), sys.executable, "-m", "sogm_service", "demo",
                     "--zenoh-config", str(fleet), "--map", "default",
                     "--duration", f"{DURATION_S:g}", "--speed", f"{SPEED:g}",
                     "--out", str(tmp_path / "out"), "--quiet"],
                    capture_output=True, text=True, timeout=180)
                rx1, tx1 = link.host_bytes()
                sub.undeclare()
            finally:
                watcher.close()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    summary: dict[str, Any] = json.loads((tmp_path / "out" / "summary.json").read_text())
    published, fused = summary["isms_published"], summary["isms_fused"]
    assert published > 0 and fused == published and summary["isms_rejected"] == 0, summary
    assert raw.isms == published  # every ISM crossed the link once
    latency = summary["submap_latency_ms"]
    assert latency["p99"] > 0, latency  # the demo's sub-map queries were answered
    crossed = (rx1 - rx0) + (tx1 - tx0)
    print(f"\nthin link (20 Mbit/s, shm off): {published} ISMs published, {fused} fused; "
          f"sub-map through the link p50 {latency['p50']:.1f} ms, p99 {latency['p99']:.1f} ms; "
          f"{crossed / 1e6:.2f} MB crossed (up {(rx1 - rx0) / 1e6:.2f}, down "
          f"{(tx1 - tx0) / 1e6:.2f}); the ISMs {raw.sent / 1e6:.2f} MB as sent, "
          f"{raw.raw / 1e6:.2f} MB raw")
    assert crossed < raw.raw / 5, (crossed, raw.raw)
