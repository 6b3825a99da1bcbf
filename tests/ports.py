"""Free TCP ports for the servers a test or a benchmark starts.

A module of its own, importing nothing of the project, so that the benchmarks' helper
processes use the same port ranges as the tests that run them.
"""

from __future__ import annotations

import os
import socket

#: Under pytest-xdist each worker takes its ports from a range of its own (the root
#: conftest sets ``IOUV_TEST_PORTS`` to "first-last" for each worker), so that a port
#: one worker found free cannot be handed to another worker's server before its own
#: server binds it. Without it (one process), the kernel picks any free port.
_PORTS = os.environ.get("IOUV_TEST_PORTS", "")
_next_port: list[int] = []


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now, for a server a test is about to start."""
    if not _PORTS:
        with socket.socket() as s:
            s.bind((host, 0))
            return int(s.getsockname()[1])
    first, last = (int(p) for p in _PORTS.split("-"))
    if not _next_port:
        _next_port.append(first)
    for _ in range(last - first + 1):
        port = _next_port[0]
        _next_port[0] = first + (port + 1 - first) % (last - first + 1)
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue  # still held (TIME_WAIT, a server of an earlier test)
            return port
    raise RuntimeError(f"no free port in {_PORTS}")
