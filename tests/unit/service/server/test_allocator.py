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
