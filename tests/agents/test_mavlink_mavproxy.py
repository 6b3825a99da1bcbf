"""Third-party conformance: MAVProxy, a stock ground station from PyPI, flies the
simulator without asking for a single telemetry stream, and reads its altitude.

MAVProxy asks for streams (REQUEST_DATA_STREAM, every stream at ``--streamrate`` Hz) only
for vehicles it has already seen, and then every 15 s; ``--streamrate -1`` turns that off.
So the altitude it shows here is what the simulator streams by itself. MAVProxy is driven
as a person would: commands typed on its console (``mode``, ``arm``, ``takeoff``,
``status``), answers read from its output.
"""

from __future__ import annotations

import queue
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

pytest.importorskip("MAVProxy", reason="needs MAVProxy (the dev extras)")

ROOT = Path(__file__).resolve().parents[2]
HOME = (40.6306, -8.6588)
#: What MAVProxy's ``status GLOBAL_POSITION_INT`` prints of the message.
POSITION_LINE = re.compile(r"GLOBAL_POSITION_INT \{.*\brelative_alt : (-?\d+)")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Console:
    """MAVProxy's console: type a line, wait for an output line."""

    def __init__(self, process: subprocess.Popen[str]) -> None:
        self.process = process
        self.lines: queue.Queue[str] = queue.Queue()
        self.transcript: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.put(line.rstrip("\n"))

    def type(self, line: str) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()

    def wait_for(
        self, match: Callable[[str], object], within: float, what: str, *, repeat: str = ""
    ) -> object:
        """The first truthy ``match(line)``; ``repeat`` is typed again every half second."""
        deadline = time.monotonic() + within
        next_repeat = 0.0
        while (left := deadline - time.monotonic()) > 0:
            if repeat and time.monotonic() >= next_repeat:
                self.type(repeat)
                next_repeat = time.monotonic() + 0.5
            try:
                line = self.lines.get(timeout=min(0.2, left))
            except queue.Empty:
                continue
            self.transcript.append(line)
            found = match(line)
            if found:
                return found
        tail = "\n".join(self.transcript[-30:])
        raise AssertionError(f"MAVProxy never showed {what} within {within:g} s; it said:\n{tail}")


@pytest.fixture
def flown(tmp_path: Path) -> Iterator[tuple[Console, Path]]:
    """MAVProxy listening on a UDP port and the simulator (4x flight time, every message
    it receives logged) sending to it; both stopped afterwards."""
    port = _free_udp_port()
    mavproxy = subprocess.Popen(
        [
            sys.executable, "-m", "MAVProxy.mavproxy",
            "--master", f"udpin:127.0.0.1:{port}",
            "--streamrate=-1",  # never ask for streams
            "--no-state", "--state-basedir", str(tmp_path),
            "--default-modules", "mode,arm,cmdlong",
        ],
        cwd=tmp_path, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True, bufsize=1,
    )  # fmt: skip
    received = tmp_path / "simulator.log"
    with received.open("w") as log:
        sim = subprocess.Popen(
            [
                sys.executable, "-m", "agents", "sim", "mavlink",
                "--connect", f"udpout:127.0.0.1:{port}",
                "--home", f"{HOME[0]},{HOME[1]}",
                "--speedup", "4", "--log-level", "DEBUG",
            ],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=log,
        )  # fmt: skip
    try:
        yield Console(mavproxy), received
    finally:
        for process in (mavproxy, sim):
            process.terminate()
        for process in (mavproxy, sim):
            try:
                process.wait(5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def test_mavproxy_reads_the_altitude_without_asking_for_a_stream(flown):
    console, received = flown
    console.wait_for(lambda line: "Detected vehicle 1:1" in line, 60, "the vehicle")

    # On the ground: the simulator's own stream, never asked for.
    found = console.wait_for(
        POSITION_LINE.search, 10, "GLOBAL_POSITION_INT", repeat="status GLOBAL_POSITION_INT"
    )
    assert isinstance(found, re.Match) and abs(int(found[1])) < 200  # mm above home

    console.type("mode GUIDED")
    console.wait_for(lambda line: "DO_SET_MODE: ACCEPTED" in line, 10, "GUIDED accepted")
    console.type("arm throttle")
    console.wait_for(lambda line: "ARMED" in line, 10, "the armed copter")
    console.type("takeoff 3")
    console.wait_for(lambda line: "NAV_TAKEOFF: ACCEPTED" in line, 10, "the take-off accepted")

    def at_3_m(line: str) -> re.Match[str] | None:
        found = POSITION_LINE.search(line)
        return found if found and int(found[1]) > 2800 else None

    found = console.wait_for(at_3_m, 20, "3 m", repeat="status GLOBAL_POSITION_INT")
    assert isinstance(found, re.Match) and int(found[1]) < 3300

    # Nothing asked for a stream: no REQUEST_DATA_STREAM, no SET_MESSAGE_INTERVAL (511).
    log = received.read_text()
    assert "COMMAND_LONG" in log  # the simulator does log what it receives
    assert "REQUEST_DATA_STREAM" not in log
    assert "command : 511," not in log
