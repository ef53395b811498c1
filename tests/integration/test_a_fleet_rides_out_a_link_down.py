"""A fleet in its own network namespace whose veth goes down for 12 s (longer than Zenoh's
10 s lease, so the silent link is noticed late) and stays down past the fleet's end: every
ISM put since went into the dead link.  No exception escapes, each key's newest ISM is fused
all the same (sent again once the server's acknowledgements say it never arrived), and every
ISM is accounted for (fused, dropped by the offline policy, or lost in flight).  Needs root
and ``ip``; every namespace and link made here is removed."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import start_server, wait_processed

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0
                                 or shutil.which("ip") is None,
                                 reason="needs root and iproute2 for a network namespace")]

FLEET = """
import json, sys
from sogm_service.sim import warehouse_world
from sogm_service.sim.fleet import run_fleet
st = run_fleet(warehouse_world(0), sys.argv[1], robots=2, duration_s=8.0, rate_hz=4.0,
               seed=1, realtime=True, flush_s=16.0)
print(json.dumps({**st.__dict__, "isms_sent": st.isms_sent}))
"""


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


def test_a_fleet_in_a_namespace_rides_out_its_link_down(tmp_path: Path) -> None:
    tag = f"sogmdo{os.getpid() % 100000}"
    ns, host_if, ns_if = tag, f"{tag}a", f"{tag}b"
    made_ns = made_link = False
    try:
        ip("netns", "add", ns)
        made_ns = True
        ip("link", "add", host_if, "type", "veth", "peer", "name", ns_if)
        made_link = True
        ip("link", "set", ns_if, "netns", ns)
        ip("addr", "add", "10.203.9.1/30", "dev", host_if)
        ip("link", "set", host_if, "up")
        ip("netns", "exec", ns, "ip", "addr", "add", "10.203.9.2/30", "dev", ns_if)
        ip("netns", "exec", ns, "ip", "link", "set", ns_if, "up")
        srv = start_server(tmp_path, {"zenoh": {"listen": ["tcp/10.203.9.1:17449"]}})
        try:
            fleet = subprocess.Popen(
                ["ip", "netns", "exec", ns, sys.executable, "-c", FLEET, srv.endpoint],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=Path(__file__).parents[2])
            time.sleep(4.0)
            ip("link", "set", host_if, "down")
            time.sleep(12.0)
            ip("link", "set", host_if, "up")
            out, err = fleet.communicate(timeout=90)
            assert fleet.returncode == 0, err.decode()[-2000:]  # no exception escaped
            stats = json.loads(out.decode().strip().splitlines()[-1])
            with srv.client() as client:
                counters = wait_processed(client, stats["isms_sent"] - stats["isms_lost"])
                newest = {key: client.ack(ism_id, 2.0).status
                          for key, ism_id in stats["last_ids"].items()}
            fused = counters.get("isms_fused", 0)
            print(f"offered {stats['isms']}, fused {fused}, dropped {stats['isms_dropped']}, "
                  f"lost {stats['isms_lost']}, resent {stats['isms_resent']}")
            # The newest ISM of every key went into the silent link; it is in the map.
            assert len(newest) >= 4 and set(newest.values()) == {"fused"}, (newest, stats)
            assert stats["isms_resent"] == len(newest), stats
            assert stats["isms_dropped"] > 0 and stats["isms_lost"] == 0, stats
            assert fused + stats["isms_dropped"] + stats["isms_lost"] == stats["isms"], \
                (counters, stats)
        finally:
            assert srv.terminate() == 0
    finally:
        if made_link:
            subprocess.run(["ip", "link", "del", host_if], capture_output=True, timeout=10)
        if made_ns:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
