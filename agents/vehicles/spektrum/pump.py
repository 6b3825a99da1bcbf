"""Getting frames out on time: the frame pump process, its thread fallback, and the
threads that tick the controls and read the return line.

Timing (why neither the asyncio loop nor a thread): the FC wants a frame every 11 ms
whatever the network, the event loop or the video encoder is doing. A Python thread
shares the interpreter lock with the event loop, and with a CPU-heavy coroutine on the
loop its wake-ups came 5-50 ms late (measured: mean period 16-19 ms). So, like the
paper's dedicated microcontroller, a small **frame pump process** owns the schedule
(:class:`FramePump`, :func:`frame_pump_main`): it sleeps until deadlines on a fixed
monotonic grid (:class:`FrameSchedule`: lateness never accumulates), writes each frame
to the port's file descriptor, runs with real-time priority when permitted, and stops
sending (a receiver loss for the FC) if the agent stops feeding it. In the agent, a
control thread (:class:`ControlTicker`) ticks the virtual sticks every 10 ms and sends
the servo positions to the pump; a reader thread (:class:`ReturnReader`) takes what
comes back on the line. Ports without a file descriptor (pyserial URLs such as
``loop://``) fall back to a writer thread (:class:`FrameWriter`).
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import json
import logging
import math
import os
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agents.vehicles.spektrum.config import SpektrumConfig
from agents.vehicles.spektrum.controls import FlightControls
from agents.vehicles.spektrum.frames import SYSTEM_DSMX_11MS, clamp_servo, frame_for
from agents.vehicles.spektrum.report import ReturnLineParser

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameTiming:
    """Frame timing over a window: periods in ms between consecutive frame writes."""

    count: int
    mean_ms: float | None
    p99_dev_ms: float | None  # 99th percentile of |period - nominal|
    max_ms: float | None


def timing_of(stamps: Sequence[float], nominal_ms: float) -> FrameTiming:
    """Period statistics of monotonic write times ``stamps`` (seconds, ascending)."""
    periods = [(b - a) * 1000.0 for a, b in itertools.pairwise(stamps)]
    if not periods:
        return FrameTiming(0, None, None, None)
    devs = sorted(abs(p - nominal_ms) for p in periods)
    p99 = devs[min(len(devs) - 1, math.ceil(0.99 * len(devs)) - 1)]
    return FrameTiming(len(periods), sum(periods) / len(periods), p99, max(periods))


class FrameSchedule:
    """Deadlines on a fixed monotonic grid: ``start + k * period``.

    After each frame the next deadline is one period on, whatever time the frame
    actually went out, so a late wake-up never shifts the following frames and lateness
    does not accumulate. When a frame went out more than half a period late (a stall),
    whole grid slots are skipped rather than sending the next frame right behind it: a
    receiver delimits frames only by the silence between them and would merge the two.
    """

    def __init__(self, period_s: float, start: float) -> None:
        self.period = period_s
        self.next_at = start
        self.skipped = 0

    def advance(self, now: float) -> float:
        """The deadline after the slot just served at ``now``."""
        self.next_at += self.period
        if self.next_at - now < self.period / 2:
            skip = math.ceil((now + self.period / 2 - self.next_at) / self.period)
            self.next_at += skip * self.period
            self.skipped += skip
        return self.next_at


class FrameStats:
    """Counters and write times of the frames sent, shared between threads."""

    def __init__(self) -> None:
        self.frames = 0
        self.write_errors = 0
        self.skipped_slots = 0
        self.starved = 0
        self.realtime = False
        self.stamps: collections.deque[float] = collections.deque(maxlen=8192)
        self.changed = threading.Condition()

    def add(self, stamps: Sequence[float], *, errors: int = 0) -> None:
        with self.changed:
            self.stamps.extend(stamps)
            self.frames += len(stamps)
            self.write_errors += errors
            self.changed.notify_all()

    def wait_frames(self, count: int, timeout: float) -> bool:
        """Block until ``count`` more frames went out."""
        with self.changed:
            target = self.frames + count
            return self.changed.wait_for(lambda: self.frames >= target, timeout)


def _log_every(count: int) -> bool:
    return count in (1, 10, 100) or count % 1000 == 0


class FrameWriter(threading.Thread):
    """The frame schedule on a thread of the agent's process (``writer: "thread"``,
    and for ports without a file descriptor such as ``loop://``).

    Each slot ticks the controls and writes one frame. It shares the interpreter lock
    with the event loop, so a CPU-heavy loop delays its wake-ups (the process writer
    does not have that problem).
    """

    def __init__(
        self, port: Any, controls: FlightControls, config: SpektrumConfig, fc: Any
    ) -> None:
        super().__init__(name="spektrum-writer", daemon=True)
        self.port = port
        self.controls = controls
        self.config = config
        self.fc = fc  # () -> FcReport | None
        self.stop_event = threading.Event()
        self.stats = FrameStats()

    def run(self) -> None:
        schedule = FrameSchedule(self.config.period_s, time.monotonic())
        phase = False
        while not self.stop_event.is_set():
            now = time.monotonic()
            try:
                values = self.controls.tick(now, self.fc())
                self.port.write(frame_for(values, phase=phase, system=self.config.system))
            except Exception as exc:  # a dead port must not kill the schedule
                self.stats.add((), errors=1)
                if _log_every(self.stats.write_errors):
                    logger.warning("spektrum: frame write failed: %s", exc)
            else:
                self.stats.add((now,))
                phase = not phase  # A, B, A, ... as received, whatever was lost
            next_at = schedule.advance(now)
            self.stats.skipped_slots = schedule.skipped
            self.stop_event.wait(next_at - time.monotonic())

    def publish(self, values: Sequence[int]) -> None:
        """Nothing to do: this writer ticks the controls itself at every frame."""

    def stop(self) -> None:
        self.stop_event.set()


#: A control record from the agent to the pump: magic, then the eight positions.
PUMP_RECORD = struct.Struct("<4s8H")
PUMP_MAGIC = b"SPK1"
#: The pump reports its counters and frame times this often.
PUMP_STATUS_S = 0.025
_PUMP_BOOT = (
    "import sys; from agents.vehicles.spektrum.pump import frame_pump_main; "
    "sys.exit(frame_pump_main(sys.argv[1:]))"
)


def _child_env() -> dict[str, str]:
    """The environment for a child ``python``: this checkout importable as ``agents``."""
    root = str(Path(__file__).resolve().parents[3])
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path}


class FramePump:
    """The agent's side of the frame pump process (``writer: "process"``).

    The pump is the paper's dedicated microcontroller: a small process that only writes
    frames on the schedule, with its own interpreter (so the event loop, the video
    encoder or a burst of commands cannot delay it) and, when permitted, real-time
    scheduling. It writes to the port's file descriptor, inherited. The agent sends it
    the eight servo positions over a pipe whenever the controls tick (every 10 ms and
    after each command); it sends back its counters and frame times every 25 ms.

    If the agent stops sending (hung, killed) for ``pump_stale_s``, the pump stops
    writing frames, exactly like a receiver that lost its transmitter: the FC then runs
    its own receiver-loss fail-safe. It exits when the agent closes the pipe or dies.
    """

    def __init__(self, port_fd: int, config: SpektrumConfig) -> None:
        self.port_fd = port_fd
        self.config = config
        self.stats = FrameStats()
        self.process: subprocess.Popen[bytes] | None = None
        self.dropped = 0
        self._control: int | None = None
        self._status: int | None = None
        self._reader: threading.Thread | None = None

    def start(self) -> None:
        cfg = self.config
        control_r, control_w = os.pipe()
        status_r, status_w = os.pipe()
        args = [
            "--port-fd", str(self.port_fd),
            "--control-fd", str(control_r),
            "--status-fd", str(status_w),
            "--period-ms", repr(cfg.frame_period_ms),
            "--system", str(cfg.system),
            "--stale-s", repr(cfg.pump_stale_s),
        ]  # fmt: skip
        if cfg.pump_realtime:
            args.append("--realtime")
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-c", _PUMP_BOOT, *args],
                pass_fds=(self.port_fd, control_r, status_w),
                stdin=subprocess.DEVNULL,
                env=_child_env(),
            )
        except BaseException:
            for fd in (control_r, control_w, status_r, status_w):
                os.close(fd)
            raise
        os.close(control_r)
        os.close(status_w)
        os.set_blocking(control_w, False)
        self._control, self._status = control_w, status_r
        self._reader = threading.Thread(target=self._read_status, name="spektrum-pump-status")
        self._reader.daemon = True
        self._reader.start()

    def publish(self, values: Sequence[int]) -> None:
        """Send the positions to the pump. Never blocks: 20-byte writes to a pipe are
        atomic, and if the pipe is full (the pump is stuck) the record is dropped."""
        fd = self._control
        if fd is None:
            return
        try:
            os.write(fd, PUMP_RECORD.pack(PUMP_MAGIC, *values))
        except (BlockingIOError, BrokenPipeError, OSError):
            self.dropped += 1
            if _log_every(self.dropped):
                logger.warning("spektrum: frame pump not taking positions (%d)", self.dropped)

    def _read_status(self) -> None:
        fd = self._status
        assert fd is not None
        buffer = b""
        while True:
            try:
                data = os.read(fd, 65536)
            except OSError:
                return
            if not data:
                return  # the pump exited
            buffer += data
            *lines, buffer = buffer.split(b"\n")
            if len(buffer) > 1 << 20:
                buffer = b""  # never from our own pump; bounded anyway
            for line in lines:
                self._status_line(line)

    def _status_line(self, line: bytes) -> None:
        try:
            status = json.loads(line)
            stamps = [float(t) for t in status["stamps"]]
            errors = int(status["errors"])
        except (ValueError, TypeError, KeyError):
            return
        stats = self.stats
        stats.skipped_slots = int(status.get("skipped", 0))
        stats.starved = int(status.get("starved", 0))
        stats.realtime = bool(status.get("realtime", False))
        stats.add(stamps, errors=max(0, errors - stats.write_errors))

    def is_alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def stop(self) -> None:
        """Close the control pipe: the pump sees end-of-file and exits."""
        fd, self._control = self._control, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    def join(self, timeout: float) -> None:
        """Wait for the pump to exit (killing it after ``timeout``), then its reader."""
        self.stop()
        if self.process is not None:
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self._reader is not None:
            self._reader.join(timeout)
        fd, self._status = self._status, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)


def frame_pump_main(argv: Sequence[str]) -> int:
    """The frame pump process (see :class:`FramePump`). Returns 0 when the agent
    closed the control pipe, 2 on bad arguments."""
    import argparse
    import select

    parser = argparse.ArgumentParser(prog="spektrum frame pump")
    parser.add_argument("--port-fd", type=int, required=True)
    parser.add_argument("--control-fd", type=int, required=True)
    parser.add_argument("--status-fd", type=int, required=True)
    parser.add_argument("--period-ms", type=float, default=11.0)
    parser.add_argument("--system", type=int, default=SYSTEM_DSMX_11MS)
    parser.add_argument("--stale-s", type=float, default=1.0)
    parser.add_argument("--realtime", action="store_true")
    args = parser.parse_args(list(argv))
    realtime = False
    if args.realtime:
        # SCHED_FIFO: woken on time even when every core is busy. Needs root or
        # CAP_SYS_NICE; without, the pump still has its own interpreter.
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            realtime = True
        except (AttributeError, OSError):
            pass
    control, status, port = args.control_fd, args.status_fd, args.port_fd
    os.set_blocking(control, False)
    os.set_blocking(status, False)
    period = args.period_ms / 1000.0
    values: tuple[int, ...] | None = None
    received_at = 0.0
    buffer = b""
    phase = False
    stamps: list[float] = []
    errors = starved = 0
    schedule = FrameSchedule(period, time.monotonic())
    status_at = schedule.next_at + PUMP_STATUS_S
    while True:
        timeout = max(0.0, min(schedule.next_at, status_at) - time.monotonic())
        ready, _, _ = select.select([control], [], [], timeout)
        if ready:
            try:
                data = os.read(control, 4096)
            except BlockingIOError:
                data = None
            if data == b"":
                return 0  # the agent closed the pipe (or died): stop sending frames
            buffer += data or b""
            while len(buffer) >= PUMP_RECORD.size:
                magic, *positions = PUMP_RECORD.unpack_from(buffer)
                if magic != PUMP_MAGIC:
                    buffer = buffer[1:]  # resynchronise; never expected on a pipe
                    continue
                buffer = buffer[PUMP_RECORD.size :]
                values = tuple(clamp_servo(p) for p in positions)
                received_at = time.monotonic()
        now = time.monotonic()
        if now >= schedule.next_at:
            if values is not None and now - received_at <= args.stale_s:
                try:
                    os.write(port, frame_for(values, phase=phase, system=args.system))
                    stamps.append(now)
                    phase = not phase  # A, B, A, ... as received, whatever was lost
                except OSError:
                    errors += 1
            else:
                starved += 1
            schedule.advance(now)
        if now >= status_at:
            line = json.dumps(
                {
                    "stamps": stamps,
                    "errors": errors,
                    "skipped": schedule.skipped,
                    "starved": starved,
                    "realtime": realtime,
                }
            )
            try:
                os.write(status, line.encode() + b"\n")
                stamps = []
            except BlockingIOError:
                pass  # the agent is not reading: keep the times for the next report
            except OSError:
                return 0  # the agent is gone
            if len(stamps) > 4096:
                stamps = stamps[-4096:]
            status_at = max(status_at + PUMP_STATUS_S, now)


class ControlTicker(threading.Thread):
    """With the pump: ticks the controls every 10 ms (hold timeouts, landing, the loop
    watchdog) and publishes the positions. Not time-critical; the pump keeps the frame
    timing."""

    def __init__(self, controls: FlightControls, pump: FramePump, fc: Any) -> None:
        super().__init__(name="spektrum-controls", daemon=True)
        self.controls = controls
        self.pump = pump
        self.fc = fc
        self.stop_event = threading.Event()

    def run(self) -> None:
        while not self.stop_event.is_set():
            try:
                self.pump.publish(self.controls.tick(time.monotonic(), self.fc()))
            except Exception:  # keep ticking: a dead ticker would freeze the sticks
                logger.exception("spektrum: control tick failed")
            self.stop_event.wait(0.01)


class ReturnReader(threading.Thread):
    """Reads the return line into a :class:`ReturnLineParser` until stopped."""

    def __init__(self, port: Any, parser: ReturnLineParser) -> None:
        super().__init__(name="spektrum-reader", daemon=True)
        self.port = port
        self.parser = parser
        self.stop_event = threading.Event()
        self.errors = 0

    def run(self) -> None:
        while not self.stop_event.is_set():
            try:
                waiting = self.port.in_waiting
                data = self.port.read(max(1, min(int(waiting), 4096)))
                if data:
                    self.parser.feed(bytes(data), time.monotonic())
            except Exception as exc:  # a flaky or closed line must not end the agent
                if self.stop_event.is_set():
                    return
                self.errors += 1
                if self.errors in (1, 10, 100) or self.errors % 1000 == 0:
                    logger.warning("spektrum: return line read failed: %s", exc)
                self.stop_event.wait(0.1)
