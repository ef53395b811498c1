"""The allocator tuning of the long-running commands (glibc's mallopt)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")

PROBE = ("import sys; from sogm_service.service.server.allocator import keep_large_allocations; "
         "print(keep_large_allocations())")


def _probe(env: dict[str, str]) -> str:
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                         check=True, timeout=60, env=env)
    return out.stdout.strip()


@glibc
def test_glibc_takes_the_settings() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    assert _probe(env) == "True"


@glibc
def test_an_explicit_environment_setting_wins() -> None:
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "131072"}
    assert _probe(env) == "False"


def test_only_long_running_commands_tune() -> None:
    from sogm_service.apps.cli import _LONG_RUNNING

    assert {"serve", "demo", "replay", "bench"} <= _LONG_RUNNING
    assert not {"query", "publish-ism", "schemas"} & _LONG_RUNNING


GIVE_BACK = """
import ctypes, sys
from pathlib import Path
import numpy as np
from sogm_service.service.server.allocator import give_back, keep_large_allocations

def rss_mb():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024

keep_large_allocations()
blocks = [np.ones(65536, np.int16) for _ in range(2000)]  # 250 MiB of 128 KiB planes, heap
del blocks[::2]                                           # every other one freed: holes
before = rss_mb()
released = give_back()
print(released, round(before - rss_mb()))
"""


@glibc
def test_give_back_returns_the_holes_between_live_blocks() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", GIVE_BACK], capture_output=True, text=True,
                         check=True, timeout=60, env=env)
    released, freed_mb = out.stdout.split()
    assert released == "True"
    assert int(freed_mb) >= 100  # of the 125 MiB freed between live blocks
