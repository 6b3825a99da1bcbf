"""``bin/demo`` run while a demo already runs: it says so and touches nothing.

A second demo from the same folder would seed var/ again (the running demo's vehicles
would get new credentials and their agents be refused), and one on a port already taken
would report the other platform, which answers its health check, as its own. Both are
refused before anything is installed, migrated or seeded.
"""

from __future__ import annotations

import fcntl
import os
import socket
import subprocess

from tests.servers import ROOT, free_port


def _demo(port: int) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(ROOT / "bin" / "demo")],
        cwd=ROOT,
        env={**os.environ, "PORT": str(port)},
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_demo_on_a_port_in_use_is_refused_before_anything_is_done() -> None:
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        run = _demo(port)
    assert run.returncode == 1
    assert f"Port {port} is already in use" in run.stderr
    assert "PORT=8100 bin/demo" in run.stderr
    assert run.stdout == ""  # nothing set up, migrated or seeded


def test_a_second_demo_from_the_same_folder_is_refused() -> None:
    (ROOT / "var").mkdir(exist_ok=True)
    with open(ROOT / "var" / "demo.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a demo running here
        run = _demo(free_port())
    assert run.returncode == 1
    assert "A demo from this folder is already running" in run.stderr
    assert run.stdout == ""
