"""Free TCP ports on 127.0.0.1 for the servers that the integration test and the
tests start as child processes.

A port from ``bind(("127.0.0.1", 0))`` is free only until the kernel hands it
out again, and it hands out the same range for every outgoing connection: when
two test suites run side by side, a server restarted on its old port, or a child
that binds a second after its parent chose the port, can find it taken by some
other process's connection. So ports here come from below the kernel's ephemeral
range (``/proc/sys/net/ipv4/ip_local_port_range``) and above Ray's worker ports
(10002-19999), where only an explicit bind can take them, and one process never
hands out the same port twice.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

LOWEST_PORT = 20000
"""Lowest port handed out: above Ray's default worker ports (10002-19999)."""

_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_handed_out: set[int] = set()
_random = random.SystemRandom()  # two processes started at once must not draw the same ports


def _ephemeral_low() -> int:
    try:
        return int(_EPHEMERAL_RANGE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0


def _bindable(port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now, outside the kernel's ephemeral range
    when it leaves room below it, and not handed out before by this process."""
    high = _ephemeral_low()
    if high - LOWEST_PORT >= 1000:
        for _ in range(200):
            port = _random.randrange(LOWEST_PORT, high)
            if port not in _handed_out and _bindable(port):
                _handed_out.add(port)
                return port
    while True:  # no room below the ephemeral range: let the kernel choose
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        if port not in _handed_out:
            _handed_out.add(port)
            return port
