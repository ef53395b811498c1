"""Waiting for a child's TCP listener (used by the test fixtures and the bench)."""

from __future__ import annotations

import socket
import time

import pytest

from sogm_service.client.session import free_tcp_endpoint, wait_listening


def test_returns_once_something_listens() -> None:
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        endpoint = f"tcp/127.0.0.1:{server.getsockname()[1]}"
        wait_listening(endpoint, 5.0, lambda: False, lambda: "")


def test_a_dead_process_fails_at_once_with_its_log() -> None:
    started = time.monotonic()
    with pytest.raises(RuntimeError, match=r"(?s)exited before listening.*boom"):
        wait_listening(free_tcp_endpoint(), 30.0, lambda: True, lambda: "boom")
    assert time.monotonic() - started < 10.0  # not the 30 s timeout


def test_nothing_listening_times_out_with_the_log() -> None:
    with pytest.raises(RuntimeError, match=r"(?s)nothing listens.*still starting"):
        wait_listening(free_tcp_endpoint(), 0.2, lambda: False, lambda: "still starting")
