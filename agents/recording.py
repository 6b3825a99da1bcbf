"""The flight record: what the vehicle did in each session, kept on the vehicle and
uploaded to the platform (docs/records.md).

One :class:`FlightRecorder` per agent. While a task runs it numbers every sample of
that session from 1 without a gap: the telemetry track (sampled by its own loop, faster
while the vehicle moves), every command with its source, acknowledgement and age, every
event the agent reports (refusals, envelope interventions, fail-safes), and for a
MAVLink vehicle the raw stream in the ``.tlog`` format (each message behind its 8-byte
big-endian microsecond Unix timestamp), carried in ``tlog`` samples.

Samples are gathered into ``record`` batches that are written to disk (one file each,
under ``<directory>/<session>/``) before they are sent (through an
:class:`agents.outbox.AckedOutbox`), and deleted only when the platform acknowledges
them, so an uplink outage or an agent restart loses nothing.
The disk is bounded: when the batches waiting reach ``max_bytes`` the recorder stops
writing telemetry and ``tlog`` samples (commands and events, which are small and what an
investigation needs first, go on until twice the bound) and, once there is room again,
writes a ``dropped`` sample saying how much it left out. The numbering stays
contiguous: what is dropped never got a number.

The rest of the agent sees the small :class:`RecordSink` interface; the control hub,
the runtime and the adapter's raw-frame hook call it, nothing else writes the record.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import json
import logging
import os
import struct
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Final, Literal, Protocol, Self

import msgspec

from agents.config import RECORD_MAX_BYTES
from agents.outbox import AckedOutbox, Build, UplinkPort
from agents.protocol import MAX_MESSAGE_BYTES
from agents.protocol.messages import Ack, Record, RecordSample
from agents.vehicles.base import VehicleState

log = logging.getLogger(__name__)

#: Who made a command happen: the user, an autonomous mission, the platform (the end
#: of a task, a revoke), the agent's fail-safe (link lost, shutdown), the safety
#: envelope bringing the vehicle back inside its limits.
Source = Literal["user", "mission", "platform", "failsafe", "safety"]

#: Telemetry samples a second while the vehicle moves (armed, airborne or under way),
#: and while it stands still.
MOVING_HZ: Final = 5.0
STILL_HZ: Final = 1.0
#: A batch is closed and written this often, or sooner when it reaches BATCH_BYTES.
BATCH_S: Final = 1.0
#: Encoded samples in one batch at most: the frame stays well under the protocol's
#: limit (MAX_MESSAGE_BYTES) with its envelope.
BATCH_BYTES: Final = MAX_MESSAGE_BYTES - 16 * 1024
#: Raw tlog bytes in one sample at most (base64 makes it 4/3 bigger).
TLOG_CHUNK: Final = 12 * 1024
#: Batches sent and not yet acknowledged at a time, and how long before one is sent
#: again on the same uplink.
IN_FLIGHT: Final = 8
RESEND_S: Final = 10.0

_ID_PREFIX: Final = "record:"


class RecordSink(Protocol):
    """What the agent's parts tell the flight record. Every method returns at once and
    never raises; outside a session they record nothing."""

    def command(
        self,
        *,
        source: Source,
        name: str,
        args: Mapping[str, Any],
        ok: bool,
        code: str | None = None,
        error: str | None = None,
        age_ms: float | None = None,
        seq: int | None = None,
    ) -> None:
        """A command reached its end: ``ok`` and ``code``/``error`` are its
        acknowledgement; ``age_ms`` how old it was when handled (user commands that
        carried their send time); ``seq`` the client's number for it."""

    def session_start(self, session_id: str) -> None:
        """A task of ``session_id`` became current: record it from now on."""

    def session_end(self) -> None:
        """The current task ended (after its safe action): stop recording it."""

    def event(self, name: str, session_id: str | None, data: Mapping[str, Any]) -> None:
        """An event the agent reports about ``session_id`` (recorded if it is the
        session being recorded)."""

    def raw(self, at: float, frame: bytes) -> None:
        """One raw message of the vehicle's own protocol (MAVLink), received at ``at``
        (Unix seconds)."""


class NullRecorder:
    """A :class:`RecordSink` that keeps nothing (hubs and adapters tested alone)."""

    def command(self, **_: Any) -> None:
        return None

    def session_start(self, session_id: str) -> None:
        return None

    def session_end(self) -> None:
        return None

    def event(self, name: str, session_id: str | None, data: Mapping[str, Any]) -> None:
        return None

    def raw(self, at: float, frame: bytes) -> None:
        return None


def batch_id(session_id: str, first: int) -> str:
    """The id of a session's batch starting at sample ``first`` (what ``ack`` names)."""
    return f"{_ID_PREFIX}{session_id}:{first}"


@dataclass
class _Session:
    id: str
    directory: Path
    next_seq: int = 1
    samples: list[RecordSample] = field(default_factory=list)
    size: int = 0
    tlog: bytearray = field(default_factory=bytearray)


@dataclass
class _Pending:
    path: Path
    size: int


@dataclass
class _Dropped:
    telemetry: int = 0
    tlog_bytes: int = 0
    other: int = 0

    def __bool__(self) -> bool:
        return bool(self.telemetry or self.tlog_bytes or self.other)


class FlightRecorder:
    """Records the current session and uploads its batches (module docstring).

    ``state`` and ``telemetry`` read the vehicle (never blocking); ``directory`` is where
    batches wait. Use as an async context manager: it samples and uploads until the
    block ends, then writes what it holds. :attr:`uplink` is set once the uplink exists.
    """

    def __init__(
        self,
        *,
        directory: Path,
        state: Callable[[], VehicleState],
        telemetry: Callable[[], Mapping[str, Any]],
        max_bytes: int = RECORD_MAX_BYTES,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.directory = directory
        self.state = state
        self.telemetry = telemetry
        self.max_bytes = max_bytes
        self.clock = clock
        self.session: _Session | None = None
        #: Batches on disk waiting for the platform's ack, oldest first, by id.
        self.pending: dict[str, _Pending] = {}
        #: Sends them (one unit each, by :func:`batch_id`).
        self.outbox = AckedOutbox(
            self._batches,
            in_flight=IN_FLIGHT,
            resend_s=RESEND_S,
            name="record-upload",
            what="flight record upload",
        )
        self.dropped = _Dropped()
        self._tasks: list[asyncio.Task[None]] = []
        self._last_sample = 0.0
        self._pending_bytes = 0

    @property
    def uplink(self) -> UplinkPort | None:
        """The uplink the batches go through (the outbox's)."""
        return self.outbox.uplink

    @uplink.setter
    def uplink(self, uplink: UplinkPort | None) -> None:
        self.outbox.uplink = uplink

    # --- lifecycle -----------------------------------------------------------------------
    async def __aenter__(self) -> Self:
        self.directory.mkdir(parents=True, exist_ok=True)
        self._load_pending()
        self._tasks = [asyncio.create_task(self._sample_loop(), name="record-sample")]
        self.outbox.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.outbox.stop()
        self.flush()

    def _load_pending(self) -> None:
        """Batches a previous run left unacknowledged are sent first."""
        for path in sorted(self.directory.glob("*/batch-*.json")):
            session_id = path.parent.name
            first = int(path.stem.split("-", 1)[1])
            self._pending_add(batch_id(session_id, first), _Pending(path, path.stat().st_size))

    @property
    def pending_bytes(self) -> int:
        """Bytes of the batches waiting for the platform (kept as a running total: it
        is read for every sample, and a long outage leaves thousands of batches)."""
        return self._pending_bytes

    def _pending_add(self, mid: str, pending: _Pending) -> None:
        self.pending[mid] = pending
        self._pending_bytes += pending.size

    def _pending_drop(self, mid: str) -> _Pending | None:
        pending = self.pending.pop(mid, None)
        if pending is not None:
            self._pending_bytes -= pending.size
        self.outbox.forget(mid)
        return pending

    # --- sessions ------------------------------------------------------------------------
    def session_start(self, session_id: str) -> None:
        """Record ``session_id`` from now on (again after a restart: its numbering goes
        on from the last sample written)."""
        if self.session is not None and self.session.id == session_id:
            return
        self.session_end()
        directory = self.directory / session_id
        directory.mkdir(parents=True, exist_ok=True)
        next_seq = 1
        with contextlib.suppress(OSError, ValueError, KeyError):
            next_seq = int(json.loads((directory / "state.json").read_text())["next_seq"])
        self.session = _Session(id=session_id, directory=directory, next_seq=next_seq)
        self._sample_telemetry(self.clock())

    def session_end(self) -> None:
        """Stop recording the current session, writing what it holds."""
        if self.session is not None:
            self._sample_telemetry(self.clock())
            self.flush()
            self.session = None

    # --- RecordSink ----------------------------------------------------------------------
    def command(
        self,
        *,
        source: Source,
        name: str,
        args: Mapping[str, Any],
        ok: bool,
        code: str | None = None,
        error: str | None = None,
        age_ms: float | None = None,
        seq: int | None = None,
    ) -> None:
        data: dict[str, Any] = {"source": source, "name": name, "args": dict(args), "ok": ok}
        if code is not None:
            data["code"] = code
        if error is not None:
            data["error"] = error
        if age_ms is not None:
            data["age_ms"] = round(age_ms, 1)
        if seq is not None:
            data["seq"] = seq
        self._add("command", data)

    def event(self, name: str, session_id: str | None, data: Mapping[str, Any]) -> None:
        if self.session is not None and session_id == self.session.id:
            self._add("event", {"event": name, **dict(data)})

    def raw(self, at: float, frame: bytes) -> None:
        session = self.session
        if session is None:
            return
        if self._full(kind="tlog"):
            self.dropped.tlog_bytes += len(frame)
            return
        session.tlog += struct.pack(">Q", int(at * 1e6)) + frame
        if len(session.tlog) >= TLOG_CHUNK:
            self._tlog_samples(session)

    # --- samples and batches -------------------------------------------------------------
    def _full(self, *, kind: str) -> bool:
        bound = self.max_bytes if kind in ("telemetry", "tlog") else 2 * self.max_bytes
        return self.pending_bytes >= bound

    def _add(self, kind: str, data: dict[str, Any], *, at: float | None = None) -> None:
        session = self.session
        if session is None:
            return
        if self._full(kind=kind):
            if kind == "telemetry":
                self.dropped.telemetry += 1
            else:
                self.dropped.other += 1
            return
        if self.dropped:
            # There is room again: the record says what it could not keep.
            dropped, self.dropped = self.dropped, _Dropped()
            self._append(
                session,
                "dropped",
                {
                    "reason": "the vehicle's buffer was full",
                    "telemetry": dropped.telemetry,
                    "tlog_bytes": dropped.tlog_bytes,
                    "other": dropped.other,
                },
                self.clock(),
            )
        self._append(session, kind, data, self.clock() if at is None else at)

    def _append(self, session: _Session, kind: str, data: dict[str, Any], at: float) -> None:
        sample = msgspec.convert(
            {"seq": session.next_seq, "t": round(at, 3), "kind": kind, "data": data},
            RecordSample,
        )
        size = len(msgspec.json.encode(sample))
        if session.samples and session.size + size > BATCH_BYTES:
            self._write_batch(session)
        session.next_seq += 1
        session.samples.append(sample)
        session.size += size

    def _tlog_samples(self, session: _Session) -> None:
        data, session.tlog = bytes(session.tlog), bytearray()
        for start in range(0, len(data), TLOG_CHUNK):
            chunk = data[start : start + TLOG_CHUNK]
            self._add("tlog", {"b64": base64.b64encode(chunk).decode("ascii")})

    def flush(self) -> None:
        """Write the samples gathered so far as a batch (the loop does it every
        BATCH_S)."""
        session = self.session
        if session is None:
            return
        if session.tlog:
            self._tlog_samples(session)
        if session.samples:
            self._write_batch(session)

    def _write_batch(self, session: _Session) -> None:
        samples, session.samples, session.size = session.samples, [], 0
        first = samples[0].seq
        message = Record(
            id=batch_id(session.id, first), session_id=session.id, first=first, samples=samples
        )
        body = msgspec.json.encode(message)
        path = session.directory / f"batch-{first:012d}.json"
        try:
            # Written whole, then renamed: a batch file is never half there.
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(body)
            os.replace(tmp, path)
            state = session.directory / "state.json"
            state.write_text(json.dumps({"next_seq": session.next_seq}))
        except OSError:
            log.exception("could not write flight-record batch %s", path)
            return
        self._pending_add(message.id, _Pending(path, len(body)))
        self.outbox.wake()

    def _sample_telemetry(self, at: float) -> None:
        state = self.state()
        telemetry = self.telemetry()
        data: dict[str, Any] = {
            "lat": state.lat,
            "lon": state.lon,
            "alt": state.alt,
            "heading": state.heading_deg,
            "speed": state.speed_mps,
            "battery": state.battery,
            "mode": state.mode,
            "armed": state.armed,
        }
        for topic in ("roll", "pitch", "yaw", "altitude", "in_air", "climb_rate"):
            value = telemetry.get(topic)
            if isinstance(value, int | float | bool | str):
                data[topic] = value
        self._last_sample = at
        self._add("telemetry", data, at=at)

    def _moving(self) -> bool:
        state = self.state()
        if state.armed:
            return True
        return state.speed_mps is not None and state.speed_mps > 0.2

    async def _sample_loop(self) -> None:
        last_batch = self.clock()
        while True:
            await asyncio.sleep(1 / MOVING_HZ)
            now = self.clock()
            if self.session is None:
                continue
            try:
                if self._moving() or now - self._last_sample >= 1 / STILL_HZ:
                    self._sample_telemetry(now)
                if now - last_batch >= BATCH_S:
                    last_batch = now
                    self.flush()
            except Exception:  # the vehicle goes on whatever the record does
                log.exception("flight record sampling failed")

    # --- upload --------------------------------------------------------------------------
    def acked(self, ack: Ack) -> bool:
        """The platform's ``ack`` of a batch: its file goes. False if ``ack`` is not
        about a batch. A batch the platform refused (``ok`` false: not this vehicle's
        session, say) goes too, logged: sending it again would be refused again."""
        if not ack.id.startswith(_ID_PREFIX):
            return False
        pending = self._pending_drop(ack.id)
        if pending is not None:
            if not ack.ok:
                log.error("the platform refused flight-record batch %s: %s", ack.id, ack.detail)
            with contextlib.suppress(OSError):
                pending.path.unlink()
        self.outbox.acked(ack.id)
        return True

    def _batches(self) -> Iterator[tuple[str, Build]]:
        """The batches waiting, oldest first (the outbox's units)."""
        for mid, pending in list(self.pending.items()):
            yield mid, functools.partial(self._batch, mid, pending)

    def _batch(self, mid: str, pending: _Pending) -> Record | None:
        """The batch ``mid`` as it was written; None, dropped, if it cannot be read."""
        try:
            return msgspec.json.decode(pending.path.read_bytes(), type=Record)
        except (OSError, msgspec.DecodeError, msgspec.ValidationError) as exc:
            log.error("dropped unreadable flight-record batch %s: %s", pending.path, exc)
            self._pending_drop(mid)
            return None
