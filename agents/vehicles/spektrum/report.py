"""The return line: what comes back from the far end of the receiver line.

The Convergence's flight controller sends nothing back, so on the real plane altitude,
speed, position and battery are unknown unless a companion sensor writes JSON lines
onto the return line; the simulator (:mod:`agents.vehicles.spektrum.sim`) writes the
same lines. One JSON object per line (:func:`parse_report` into an :class:`FcReport`);
anything malformed is counted and ignored (:class:`ReturnLineParser`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

#: Longest return line accepted; longer ones are dropped (and counted) whole.
MAX_RETURN_LINE = 2048

_NUMBER_FIELDS = (
    "alt",
    "vz",
    "speed",
    "airspeed",
    "heading",
    "lat",
    "lon",
    "battery",
    "period_ms",
    "jitter_ms",
    "max_gap_ms",
)
_BOOL_FIELDS = ("armed", "on_ground", "stalled", "crashed", "fc_failsafe")
_INT_FIELDS = (
    "frames",
    "bad_frames",
    "hard_landings",
    "arm_refused",
    "out_of_travel",
    "close_frames",
)
FC_MODES = ("vtol", "transition", "aircraft")


@dataclass(frozen=True)
class FcReport:
    """One state report from the far end of the line; None where not reported.

    ``mode`` is "vtol", "transition" or "aircraft"; ``alt`` metres above the take-off
    point; ``speed`` horizontal ground speed and ``airspeed`` forward speed in m/s;
    ``heading`` degrees clockwise from north; ``battery`` percent; ``period_ms``,
    ``jitter_ms`` (p99 of |period - nominal|) and ``max_gap_ms`` the frame timing as
    the receiving end measured it.
    """

    alt: float | None = None
    vz: float | None = None
    speed: float | None = None
    airspeed: float | None = None
    heading: float | None = None
    lat: float | None = None
    lon: float | None = None
    battery: float | None = None
    period_ms: float | None = None
    jitter_ms: float | None = None
    max_gap_ms: float | None = None
    armed: bool | None = None
    on_ground: bool | None = None
    stalled: bool | None = None
    crashed: bool | None = None
    fc_failsafe: bool | None = None
    frames: int | None = None
    bad_frames: int | None = None
    hard_landings: int | None = None
    arm_refused: int | None = None
    out_of_travel: int | None = None
    close_frames: int | None = None
    mode: str | None = None
    bad_reasons: Mapping[str, int] | None = None


def parse_report(line: bytes) -> FcReport:
    """Parse one return line (without its newline). Raises ValueError when it is not a
    JSON object or a known field has the wrong type or an impossible value; unknown
    fields are ignored (a newer simulator may report more)."""
    data = json.loads(line)  # bytes: JSON detects UTF-8/16/32 itself
    if not isinstance(data, dict):
        raise ValueError("a report is a JSON object")
    values: dict[str, Any] = {}
    for name in _NUMBER_FIELDS:
        value = data.get(name)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{name} must be a number")
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite")
        values[name] = float(value)
    for name in _BOOL_FIELDS:
        value = data.get(name)
        if value is None:
            continue
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be true or false")
        values[name] = value
    for name in _INT_FIELDS:
        value = data.get(name)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be a count")
        values[name] = value
    reasons = data.get("bad_reasons")
    if reasons is not None:
        if not isinstance(reasons, dict) or len(reasons) > 32:
            raise ValueError("bad_reasons must be a small object of counts")
        for count in reasons.values():
            if isinstance(count, bool) or not isinstance(count, int) or count < 0:
                raise ValueError("bad_reasons must count")
        values["bad_reasons"] = {str(k)[:32]: v for k, v in reasons.items()}
    mode = data.get("mode")
    if mode is not None:
        if mode not in FC_MODES:
            raise ValueError("mode must be vtol, transition or aircraft")
        values["mode"] = mode
    lat, lon = values.get("lat"), values.get("lon")
    if (lat is not None and not -90 <= lat <= 90) or (lon is not None and not -180 <= lon <= 180):
        raise ValueError("lat/lon out of range")
    if "battery" in values and not 0 <= values["battery"] <= 100:
        raise ValueError("battery out of range")
    return FcReport(**values)


class ReturnLineParser:
    """Splits the bytes coming back on the line into reports. Never raises.

    Lines are newline-terminated JSON objects of at most MAX_RETURN_LINE bytes. A
    longer line is discarded up to its newline, a line that does not parse is dropped;
    both are counted in :attr:`bad_lines`. Not thread-safe: one reader feeds it; the
    latest good report is published as an immutable object.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._discarding = False
        self.lines = 0
        self.bad_lines = 0
        self.bytes = 0
        self.report: FcReport | None = None
        self.report_at: float | None = None

    def feed(self, data: bytes, now: float) -> None:
        """Take ``data`` received at monotonic time ``now``."""
        self.bytes += len(data)
        start = 0
        while True:
            newline = data.find(b"\n", start)
            chunk = data[start:] if newline < 0 else data[start:newline]
            if self._discarding:
                if newline >= 0:
                    self._discarding = False
            else:
                self._buffer += chunk
                if len(self._buffer) > MAX_RETURN_LINE:
                    # A huge line: drop what we have and everything up to its newline,
                    # so the buffer stays bounded whatever the other end sends.
                    self._buffer.clear()
                    self.bad_lines += 1
                    self._discarding = newline < 0
                elif newline >= 0:
                    self._line(bytes(self._buffer), now)
                    self._buffer.clear()
            if newline < 0:
                return
            start = newline + 1

    def _line(self, line: bytes, now: float) -> None:
        line = line.strip()
        if not line:
            return
        try:
            report = parse_report(line)
        except (ValueError, TypeError, RecursionError):
            self.bad_lines += 1
            return
        self.lines += 1
        self.report = report
        self.report_at = now
