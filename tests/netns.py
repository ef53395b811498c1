"""A host per process on one machine: a network namespace behind a shaped veth pair.

:func:`shaped_namespace` makes a namespace of its own, a veth pair between it and the host
(private /30 addresses inside them only), a token bucket on both ends, and removes every
namespace and link it made, by name, when done.  It needs root with ``ip`` and ``tc``;
:func:`unavailable` says why not (the tests skip with that sentence).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Link:
    """The namespace and the veth pair: ``host_ip`` on ``host_dev``, ``ns_ip`` inside ``ns``."""

    ns: str
    host_dev: str
    ns_dev: str
    host_ip: str
    ns_ip: str

    def exec_prefix(self) -> list[str]:
        """Run a command inside the namespace: ``[*prefix, command...]``."""
        return ["ip", "netns", "exec", self.ns]

    def host_bytes(self) -> tuple[int, int]:
        """Bytes the host's end of the veth received and sent (Ethernet frames: what crossed
        the link, headers included)."""
        stats = Path("/sys/class/net") / self.host_dev / "statistics"
        return (int((stats / "rx_bytes").read_text()), int((stats / "tx_bytes").read_text()))


def unavailable() -> str | None:
    """Why a shaped namespace cannot be made here, or ``None`` when it can."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    missing = [tool for tool in ("ip", "tc") if shutil.which(tool) is None]
    if missing:
        return f"{' and '.join(missing)} not found"
    return None


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


@contextmanager
def shaped_namespace(tag: str, rate: str = "20mbit") -> Iterator[Link]:
    """A namespace ``sogm-<tag>-<pid>`` joined to the host by a veth pair, shaped to ``rate``
    both ways (``tc ... tbf rate RATE burst 64kb latency 200ms`` on each end)."""
    pid = os.getpid()
    octet = pid % 64 * 4  # a /30 of 10.213.<pid % 251>.0/24 of our own
    subnet = f"10.213.{pid % 251}"
    link = Link(ns=f"sogm-{tag}-{pid}", host_dev=f"sg{tag[:3]}{pid % 100000}h",
                ns_dev=f"sg{tag[:3]}{pid % 100000}n", host_ip=f"{subnet}.{octet + 1}",
                ns_ip=f"{subnet}.{octet + 2}")
    shape = ["root", "tbf", "rate", rate, "burst", "64kb", "latency", "200ms"]
    made_ns = made_link = False
    try:
        _ip("netns", "add", link.ns)
        made_ns = True
        _ip("link", "add", link.host_dev, "type", "veth", "peer", "name", link.ns_dev)
        made_link = True
        _ip("link", "set", link.ns_dev, "netns", link.ns)
        _ip("addr", "add", f"{link.host_ip}/30", "dev", link.host_dev)
        _ip("link", "set", link.host_dev, "up")
        inside = ["netns", "exec", link.ns, "ip"]
        _ip(*inside, "addr", "add", f"{link.ns_ip}/30", "dev", link.ns_dev)
        _ip(*inside, "link", "set", link.ns_dev, "up")
        _ip(*inside, "link", "set", "lo", "up")
        subprocess.run(["tc", "qdisc", "add", "dev", link.host_dev, *shape], check=True,
                       capture_output=True, timeout=30)
        subprocess.run(["ip", "netns", "exec", link.ns, "tc", "qdisc", "add", "dev",
                        link.ns_dev, *shape], check=True, capture_output=True, timeout=30)
        yield link
    finally:
        if made_link:  # deleting one end removes both, wherever the other lives
            subprocess.run(["ip", "link", "del", link.host_dev], capture_output=True,
                           timeout=30)
        if made_ns:
            subprocess.run(["ip", "netns", "del", link.ns], capture_output=True, timeout=30)
