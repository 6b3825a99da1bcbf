"""The simulated flight controller's end of the receiver line: the line itself and the
checks an FC's receiver input makes.

* :class:`FdLink` (a pty master, or a descriptor inherited from the agent) and
  :class:`SerialLink` (a device or pyserial URL) are the :class:`Link`;
* :class:`FrameChecker` splits the incoming bytes into frames the way FCs do (a frame is
  16 bytes after a quiet gap; Spektrum frames carry no sync byte) and checks each one:
  size, system byte, channel ids, no duplicates, the phase bit alternating A/B, each
  A+B pair covering all eight channels, positions inside 100 % travel. Bad frames are
  counted by reason and ignored. It measures the timing too: mean period, p99 of
  |period - nominal| ("jitter") and the longest gap over a sliding window.
"""

from __future__ import annotations

import collections
import contextlib
import errno
import logging
import math
import os
import select
import time
from dataclasses import dataclass
from typing import Any, Protocol

from agents.vehicles.spektrum.frames import (
    CHANNEL_COUNT,
    FRAME_SIZE,
    SERVO_HIGH,
    SERVO_LOW,
    SYSTEM_DSMX_11MS,
    FrameError,
    decode_frame,
)

logger = logging.getLogger(__name__)

#: A new frame starts after this much silence on the line, as in older ArduPilot
#: releases (today's resynchronises after 5 ms, PX4 after more than 5 ms; the gap only
#: matters while searching for a frame start, see docs/vehicles/vtol.md); frames are
#: 11 ms apart and take 1.4 ms at 115200 baud.
FRAME_GAP_S = 0.002


# --------------------------------------------------------------------------------------
# The line
# --------------------------------------------------------------------------------------


class Link(Protocol):
    """The simulator's end of the serial line."""

    def read(self, timeout: float) -> bytes:
        """Bytes available within ``timeout`` seconds (b"" if none). Raises OSError
        when the line is broken."""

    def write(self, data: bytes) -> bool:
        """Write without blocking; False when the data was dropped (line full)."""

    def close(self) -> None:
        """Release the line."""


class FdLink:
    """A file descriptor: a pty master, or one inherited from the agent (owned: closed
    by :meth:`close`)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        # Non-blocking writes: a report must never stall the simulator when nobody
        # reads the other end (the adapter closed it, or is not reading yet).
        os.set_blocking(fd, False)
        self._closed = False

    def read(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self.fd], [], [], max(0.0, timeout))
        if not ready:
            return b""
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return b""
        if not data:
            # End of file: readable for ever. Raise, so the caller backs off instead
            # of spinning (it may run with real-time priority).
            raise OSError(errno.EIO, "end of file on the line")
        return data

    def write(self, data: bytes) -> bool:
        try:
            return os.write(self.fd, data) == len(data)
        except (BlockingIOError, InterruptedError):
            return False

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            with contextlib.suppress(OSError):
                os.close(self.fd)


class SerialLink:
    """A serial port opened by pyserial (a device path or a pyserial URL)."""

    def __init__(self, port: str, baudrate: int = 115200) -> None:
        import serial  # type: ignore[import-untyped, unused-ignore]

        self.port: Any = serial.serial_for_url(port, baudrate=baudrate, timeout=0, write_timeout=0)

    def read(self, timeout: float) -> bytes:
        fileno = getattr(self.port, "fileno", None)
        if fileno is not None:
            try:
                fd = fileno()
            except Exception:  # URL handlers without a descriptor: poll below
                fd = None
            if fd is not None:
                ready, _, _ = select.select([fd], [], [], max(0.0, timeout))
                data = bytes(self.port.read(4096)) if ready else b""
                if ready and not data:
                    raise OSError(errno.EIO, "the port is readable but gives nothing")
                return data
        # URL handlers without a file descriptor (loop://): poll.
        data = bytes(self.port.read(4096))
        if not data:
            time.sleep(min(timeout, 0.001))
        return data

    def write(self, data: bytes) -> bool:
        try:
            return bool(self.port.write(data) == len(data))
        except Exception:  # pyserial's write timeout: drop the report
            return False

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.port.close()


# --------------------------------------------------------------------------------------
# Framing and timing checks
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TimingStats:
    """Frame periods over the window: mean, p99 of |period - nominal|, longest gap."""

    count: int
    period_ms: float | None
    jitter_ms: float | None
    max_gap_ms: float | None


class FrameChecker:
    """Splits received bytes into frames by the gap between them and checks them.

    Counters: :attr:`frames` (good), :attr:`bad` by reason (``short`` an incomplete
    frame before a gap, ``long`` bytes past 16 without a gap, ``size``/``channel_id``/
    ``duplicate``/``empty`` from the decoder, ``system`` a wrong system byte, ``phase``
    two frames of the same phase in a row, ``pair`` an A+B pair missing a channel),
    :attr:`out_of_travel` (good frames with a position outside 342..1706),
    :attr:`close_frames` (frames received right behind the previous one, without the
    quiet gap: decoded, but their timing is not measured; so are the bytes that, read
    after a read that brought more than a frame, complete the frame it cut).
    """

    def __init__(
        self, *, system: int = SYSTEM_DSMX_11MS, frame_period_ms: float = 11.0, window: int = 1000
    ) -> None:
        self.system = system
        self.nominal_ms = frame_period_ms
        self.frames = 0
        self.bad: collections.Counter[str] = collections.Counter()
        self.out_of_travel = 0
        self.close_frames = 0
        self.channels: dict[int, int] = {}
        self.last_good_at: float | None = None
        self._buffer = bytearray()
        self._last_byte_at: float | None = None
        self._burst_at = 0.0
        self._burst_frames = 0
        self._burst_timed = False
        self._backlog = False
        self._last_phase: bool | None = None
        self._phase_a_ids: frozenset[int] | None = None
        self._last_frame_at: float | None = None
        self._periods: collections.deque[float] = collections.deque(maxlen=window)

    @property
    def bad_frames(self) -> int:
        return sum(self.bad.values())

    def feed(self, data: bytes, now: float) -> None:
        """Take ``data`` that became readable at monotonic time ``now``."""
        if not data:
            return
        gap = self._last_byte_at is None or now - self._last_byte_at >= FRAME_GAP_S
        if (
            gap
            and self._backlog
            and self._buffer
            and (len(self._buffer) + len(data)) % FRAME_SIZE == 0
        ):
            # The last read brought more than a frame: this reader was behind the line,
            # and the kernel hands a backlog over in pieces that need not end on a frame
            # (a pty's buffers). These bytes complete the frame it cut, so the "gap" is
            # this reader's own delay, not a quiet line (the FC's UART times each byte
            # as it arrives and never sees one). Bytes that do not complete it are a
            # frame too long, as before.
            gap = False
        self._backlog = len(data) > FRAME_SIZE
        self._last_byte_at = now
        if gap:
            if self._buffer:
                # Left over after a whole frame: a burst too long; else a frame cut short.
                self.bad["long" if self._burst_frames else "short"] += 1
                self._buffer.clear()
            self._burst_at = now
            self._burst_frames = 0
            # A lone frame (or its first bytes): its arrival time is its time.
            self._burst_timed = len(data) <= FRAME_SIZE
        self._buffer += data
        while len(self._buffer) >= FRAME_SIZE:
            block = bytes(self._buffer[:FRAME_SIZE])
            del self._buffer[:FRAME_SIZE]
            if self._burst_frames == 0:
                self._frame(block, self._burst_at, timed=self._burst_timed)
            else:
                # A whole frame right behind another, with no quiet gap as this end saw
                # it. The writer never does that (it skips a slot rather); on a pty it is
                # this reader or the kernel delivering late. Decoded (every block is
                # checked), not timed.
                self.close_frames += 1
                self._frame(block, now, timed=False)
            self._burst_frames += 1

    def _frame(self, block: bytes, now: float, *, timed: bool) -> None:
        try:
            frame = decode_frame(block)
        except FrameError as exc:
            self.bad[exc.reason] += 1
            return
        if frame.system != self.system:
            self.bad["system"] += 1
            return
        if self._last_phase is not None and frame.phase == self._last_phase:
            self.bad["phase"] += 1
        self._last_phase = frame.phase
        ids = frozenset(frame.servos)
        if not frame.phase:
            self._phase_a_ids = ids
        elif self._phase_a_ids is not None and self._phase_a_ids | ids != frozenset(
            range(CHANNEL_COUNT)
        ):
            self.bad["pair"] += 1
        if any(not SERVO_LOW <= v <= SERVO_HIGH for v in frame.servos.values()):
            self.out_of_travel += 1
        self.frames += 1
        self.channels.update(frame.servos)
        if timed:
            if self._last_frame_at is not None:
                self._periods.append((now - self._last_frame_at) * 1000.0)
            self._last_frame_at = now
        else:
            self._last_frame_at = None  # the next period would be wrong too
        self.last_good_at = now

    def timing(self) -> TimingStats:
        periods = list(self._periods)
        if not periods:
            return TimingStats(0, None, None, None)
        devs = sorted(abs(p - self.nominal_ms) for p in periods)
        p99 = devs[min(len(devs) - 1, math.ceil(0.99 * len(devs)) - 1)]
        return TimingStats(len(periods), sum(periods) / len(periods), p99, max(periods))

    def reset_timing(self) -> None:
        """Forget the measured periods (a measurement starts afresh)."""
        self._periods.clear()
        self._last_frame_at = None
