"""The receiver side of the Spektrum VTOL plane: a flight controller on the far end of a
serial line (normally one side of a pty).

:class:`SpektrumSimulator` stands where the E-flite Convergence's flight controller (FC)
is: it reads and checks the frames (:class:`~.line.FrameChecker`), flies the model
(:class:`~.model.VtolModel`) with the decoded channels and writes its state back as one
JSON object per line at ``report_hz`` (the format
:func:`agents.vehicles.spektrum.report.parse_report` reads).

Threads: :meth:`SpektrumSimulator.start` runs it on its own thread (the simulator hook's
default); :func:`cli` runs it in the foreground (``python -m agents sim spektrum --port
/dev/pts/N``), also the hook's ``process`` variant, where the timing it measures is not
disturbed by the agent's own threads.

Timing caveat: a pty has no baud rate, so the measured period is when the bytes became
readable here. In-process, the simulator's thread shares the interpreter lock with the
agent, and its own wake-up latency adds to what it measures; use the process variant
for figures.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Mapping
from typing import Any

from agents.vehicles.spektrum.frames import (
    AUX1,
    CHANNEL_NAMES,
    GEAR,
    SYSTEM_DSMX_11MS,
)
from agents.vehicles.spektrum.sim.line import FdLink, FrameChecker, Link, SerialLink, TimingStats
from agents.vehicles.spektrum.sim.model import Inputs, SimParams, VtolModel

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------
# The simulator
# --------------------------------------------------------------------------------------


class SpektrumSimulator:
    """The FC end of the line: frames in, a flying model, JSON state lines out.

    ``link`` is owned (closed by :meth:`close`). ``params`` is a :class:`SimParams` or a
    mapping of its fields. Thread-safety: :meth:`snapshot`, :attr:`checker` counters
    and :attr:`model` may be read from other threads (values may be a step old).
    """

    def __init__(
        self,
        link: Link,
        *,
        origin: tuple[float, float],
        params: SimParams | Mapping[str, Any] | None = None,
        frame_period_ms: float = 11.0,
        system: int = SYSTEM_DSMX_11MS,
        mode_channel: int = GEAR,
        arm_channel: int = AUX1,
        step_hz: float = 50.0,
        report_hz: float = 20.0,
        window: int = 1000,
    ) -> None:
        if params is None:
            params = SimParams()
        elif not isinstance(params, SimParams):
            params = SimParams.from_mapping(params)
        self.link = link
        self.params = params
        self.model = VtolModel(params, origin)
        self.checker = FrameChecker(system=system, frame_period_ms=frame_period_ms, window=window)
        self.mode_channel = mode_channel
        self.arm_channel = arm_channel
        self.step_s = 1.0 / step_hz
        self.report_s = 1.0 / report_hz
        self.reports_sent = 0
        self.reports_dropped = 0
        self.link_errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started_at = time.monotonic()
        self._lock = threading.Lock()
        self._snapshot: dict[str, Any] = {}

    # --- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        """Run on a daemon thread until :meth:`close`."""
        self._thread = threading.Thread(target=self.run, name="spektrum-sim", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the thread (if any) and close the line. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        self.link.close()

    def stop(self) -> None:
        """Ask :meth:`run` to return."""
        self._stop.set()

    @property
    def running(self) -> bool:
        """Whether the thread started by :meth:`start` is alive."""
        return self._thread is not None and self._thread.is_alive()

    # --- the loop ----------------------------------------------------------------------
    def run(self) -> None:
        """Read, check, fly and report until stopped. Never raises for anything that
        comes in on the line; a broken line is retried every 50 ms."""
        now = time.monotonic()
        self._started_at = now
        last_step = now
        next_step = now + self.step_s
        next_report = now
        while not self._stop.is_set():
            timeout = min(next_step, next_report) - time.monotonic()
            try:
                data = self.link.read(max(0.0, timeout))
            except OSError as exc:
                # EIO: no one has the other side open (yet, or any more).
                self.link_errors += 1
                if exc.errno not in (errno.EIO, errno.EBADF) and self.link_errors < 3:
                    logger.warning("spektrum sim: line read failed: %s", exc)
                self._stop.wait(0.05)
                data = b""
            now = time.monotonic()
            if data:
                try:
                    self.checker.feed(data, now)
                except Exception:  # a checker bug must not take the FC down
                    logger.exception("spektrum sim: frame check failed")
            if now >= next_step:
                try:
                    self._step(min(now - last_step, 0.1), now)
                except Exception:
                    logger.exception("spektrum sim: model step failed")
                last_step = now
                next_step = max(next_step + self.step_s, now + self.step_s / 2)
            if now >= next_report:
                self._report()
                next_report = max(next_report + self.report_s, now + self.report_s / 2)

    def _step(self, dt: float, now: float) -> None:
        last = self.checker.last_good_at
        link_ok = last is not None and now - last <= self.params.failsafe_after_s
        inputs = Inputs.from_channels(
            self.checker.channels, mode_channel=self.mode_channel, arm_channel=self.arm_channel
        )
        self.model.step(dt, inputs, link_ok=link_ok)
        with self._lock:
            self._snapshot = self._state()

    def _state(self) -> dict[str, Any]:
        m = self.model
        timing = self.checker.timing()
        lat, lon = m.position

        def r(value: float | None, digits: int) -> float | None:
            return None if value is None else round(value, digits)

        return {
            "alt": round(m.alt, 3),
            "vz": round(m.vz, 3),
            "speed": round(m.speed, 3),
            "airspeed": round(m.v_forward, 3),
            "heading": round(m.heading, 2),
            "lat": round(lat, 8),
            "lon": round(lon, 8),
            "mode": m.mode,
            "armed": m.armed,
            "on_ground": m.on_ground,
            "battery": round(m.battery, 2),
            "stalled": m.stalled,
            "crashed": m.crashed,
            "hard_landings": m.hard_landings,
            "arm_refused": m.arm_refused,
            "fc_failsafe": m.fc_failsafe,
            "frames": self.checker.frames,
            "bad_frames": self.checker.bad_frames,
            "bad_reasons": dict(self.checker.bad),
            "close_frames": self.checker.close_frames,
            "out_of_travel": self.checker.out_of_travel,
            "period_ms": r(timing.period_ms, 3),
            "jitter_ms": r(timing.jitter_ms, 3),
            "max_gap_ms": r(timing.max_gap_ms, 3),
        }

    def _report(self) -> None:
        with self._lock:
            state = dict(self._snapshot) or self._state()
        line = json.dumps(state, separators=(",", ":")).encode() + b"\n"
        try:
            if self.link.write(line):
                self.reports_sent += 1
            else:
                self.reports_dropped += 1
        except OSError:
            self.reports_dropped += 1

    # --- reading from other threads ----------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """The state as last reported (the JSON line's fields)."""
        with self._lock:
            return dict(self._snapshot)

    def channels(self) -> dict[str, int]:
        """The last decoded servo position of every channel received, by name."""
        return {CHANNEL_NAMES[c]: v for c, v in sorted(self.checker.channels.items())}


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def _origin(text: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected LAT,LON") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError("latitude or longitude out of range")
    return (lat, lon)


def cli(argv: list[str]) -> int:
    """``python -m agents sim spektrum``: run the simulated FC on a serial port.

    Returns 0 when stopped (Ctrl-C or SIGTERM), 2 on bad arguments or a port that
    cannot be opened.
    """
    parser = argparse.ArgumentParser(
        prog="python -m agents sim spektrum",
        description="Simulated Spektrum-fed VTOL flight controller on a serial port. "
        "Make a pty pair with `socat -d -d pty,raw,echo=0 pty,raw,echo=0`, give one end "
        "here and the other to the agent's spektrum adapter as its port.",
    )
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", help="serial device or pyserial URL, e.g. /dev/pts/3")
    where.add_argument("--fd", type=int, help="an inherited file descriptor (the adapter's)")
    parser.add_argument("--baudrate", type=int, default=115200)
    parser.add_argument("--origin", type=_origin, default=(39.7436, -8.8071), help="LAT,LON")
    parser.add_argument("--period-ms", type=float, default=11.0, help="nominal frame period")
    parser.add_argument("--system", type=int, default=SYSTEM_DSMX_11MS, help="system byte")
    parser.add_argument("--params", default="{}", help="JSON object of model parameters")
    parser.add_argument("--status-every", type=float, default=1.0, help="seconds; 0: never")
    parser.add_argument("--quiet", action="store_true", help="no status lines")
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="SCHED_FIFO if permitted, so the timing measured is the line's, not this "
        "process's wake-up latency on a busy machine",
    )
    parser.add_argument("--log-level", default="WARNING")
    args = parser.parse_args(argv)
    if args.realtime:
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s: %(message)s")
    try:
        params = SimParams.from_mapping(json.loads(args.params))
    except (ValueError, TypeError, AttributeError) as exc:
        print(f"--params: {exc}", file=sys.stderr)
        return 2
    link: Link
    try:
        link = FdLink(args.fd) if args.fd is not None else SerialLink(args.port, args.baudrate)
    except Exception as exc:  # pyserial raises its own SerialException
        print(f"cannot open the line: {exc}", file=sys.stderr)
        return 2
    sim = SpektrumSimulator(
        link,
        origin=args.origin,
        params=params,
        frame_period_ms=args.period_ms,
        system=args.system,
    )
    # SIGTERM (the adapter closing its subprocess, systemd) stops cleanly like Ctrl-C.
    signal.signal(signal.SIGTERM, lambda *_: sim.stop())
    sim.start()
    try:
        while sim.running:
            time.sleep(args.status_every if args.status_every > 0 else 0.5)
            if not args.quiet and args.status_every > 0:
                print(_status_line(sim), file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()
    return 0


def _status_line(sim: SpektrumSimulator) -> str:
    s = sim.snapshot()
    if not s:
        return "no state yet"
    bad = ",".join(f"{k}={v}" for k, v in sorted(sim.checker.bad.items())) or "0"
    return (
        f"{s['mode']:<10} armed={s['armed']!s:<5} alt={s['alt']:7.2f} m "
        f"speed={s['speed']:5.2f} m/s hdg={s['heading']:6.1f} bat={s['battery']:5.1f}% | "
        f"frames={s['frames']} bad={bad} period={s['period_ms']} ms "
        f"p99|dev|={s['jitter_ms']} ms max_gap={s['max_gap_ms']} ms | "
        f"{json.dumps(sim.channels())}"
    )


__all__ = [
    "FdLink",
    "FrameChecker",
    "Inputs",
    "SerialLink",
    "SimParams",
    "SpektrumSimulator",
    "TimingStats",
    "VtolModel",
    "cli",
]
