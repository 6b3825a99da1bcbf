"""The MAVLink link to one autopilot: the port, its two threads, commands confirmed by
their COMMAND_ACK, and parameters.

Threads: pymavlink I/O blocks, so a **receiver thread** reads the link and hands each
message to the event loop (``call_soon_threadsafe``), where all state lives, and a
**writer thread** sends what the loop queues. The event loop never touches the port.

Confirmation: every MAV_CMD waits for its COMMAND_ACK (resent every ``resend_s``, with
the confirmation counter raised, until ``command_timeout_s``): ACCEPTED is the user's ok;
any other result raises :class:`~agents.vehicles.base.AdapterError` ``autopilot_refused``
with the autopilot's words: the result, and the explanation ArduPilot sends just before
its refusal (a STATUSTEXT of severity WARNING or worse received between the command's
last sending and its COMMAND_ACK), or none; never an unrelated message that happened to
come meanwhile ("Throttle armed", a pre-arm text of earlier). No answer raises
``timeout``; a link found dead meanwhile raises ``autopilot_lost``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from agents.vehicles.base import AdapterError
from agents.vehicles.mavlink.config import MavlinkConfig
from agents.vehicles.mavlink.dialect import (
    MAV,
    RESULT_HINTS,
    RESULT_WORDS,
    command_name,
    mavutil,
    param_name,
    statustext,
)

logger = logging.getLogger(__name__)


@dataclass
class _Pending:
    """A command waiting for its COMMAND_ACK."""

    command: int
    future: asyncio.Future[Any]
    sent_at: float
    #: When its COMMAND_ACK came (monotonic; texts after it answer something else).
    acked_at: float = 0.0


class AutopilotLink:
    """The link to the autopilot (see the module docstring).

    ``on_message`` gets every decoded message on the event loop (never BAD_DATA). The
    owner tells the link whether the autopilot is alive (:attr:`ok`, from its
    heartbeats) and which system and component it is (:attr:`target`); commands are
    refused while it is not ok.
    """

    def __init__(self, config: MavlinkConfig, *, on_message: Callable[[Any], None]) -> None:
        self.config = config
        self.on_message = on_message
        #: Gets (Unix time, frame) for every message sent to the autopilot, on the event
        #: loop once the writer thread has sent it (the flight record's tlog keeps both
        #: directions, as a ground station's .tlog does).
        self.on_sent: Callable[[float, bytes], None] | None = None
        self.conn: Any = None
        #: Whether the autopilot is heard (its owner keeps this up to date).
        self.ok = False
        self.target: tuple[int, int] | None = None
        if config.target_system is not None:
            self.target = (config.target_system, config.target_component or 1)
        #: Frames pymavlink could not decode (bad CRC, garbage) and unknown message ids.
        self.bad_frames = 0
        self.unknown_messages = 0
        self.send_errors = 0
        self.stats: dict[str, int] = {"acks": 0, "refusals": 0, "timeouts": 0, "setpoints": 0}
        #: The autopilot's recent STATUSTEXTs: (monotonic time, severity, text).
        self.texts: deque[tuple[float, int, str]] = deque(maxlen=20)
        self.threads: list[threading.Thread] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._out: queue.Queue[Any] = queue.Queue(maxsize=1000)
        self._stop = threading.Event()
        self._pending: dict[int, _Pending] = {}
        self._param_waiters: dict[str, list[asyncio.Future[float]]] = {}
        self._answer_waiters: list[
            tuple[tuple[str, ...], Callable[[Any], bool], asyncio.Future[Any]]
        ] = []
        self._command_lock = asyncio.Lock()

    # --- lifecycle ---------------------------------------------------------------------
    async def open(self) -> None:
        """Open the port and start the threads. Raises OSError, ValueError or
        RuntimeError (pymavlink's) when the port cannot be opened."""
        self._loop = asyncio.get_running_loop()
        self.conn = await asyncio.to_thread(self._connect)
        self.threads = [
            threading.Thread(target=self._receive, name="mavlink-receive", daemon=True),
            threading.Thread(target=self._write, name="mavlink-write", daemon=True),
        ]
        for thread in self.threads:
            thread.start()

    def _connect(self) -> Any:
        cfg = self.config
        conn = mavutil.mavlink_connection(
            cfg.connection,
            baud=cfg.baud,
            source_system=cfg.source_system,
            source_component=cfg.source_component,
            dialect="ardupilotmega",
            autoreconnect=True,
        )
        # Undecodable frames become BAD_DATA messages instead of exceptions.
        conn.mav.robust_parsing = True
        return conn

    async def close(self) -> None:
        """Stop the threads, close the port, cancel what waits for an answer. From now on
        commands are refused at once: nothing would carry them or their answers."""
        self.ok = False
        self._stop.set()
        with contextlib.suppress(queue.Full):
            self._out.put_nowait(None)
        for thread in self.threads:
            if thread.is_alive():
                await asyncio.to_thread(thread.join, 2.0)
        self.threads = []
        if self.conn is not None:
            with contextlib.suppress(Exception):
                self.conn.close()
            self.conn = None
        for pending in self._pending.values():
            if not pending.future.done():
                pending.future.cancel()
        self._pending.clear()

    def local_port(self) -> int | None:
        """The local UDP/TCP port of the link (for tests and the simulator), or None."""
        port = getattr(self.conn, "port", None)
        if port is None or not hasattr(port, "getsockname"):
            return None
        with contextlib.suppress(OSError):
            return int(port.getsockname()[1])
        return None

    # --- threads -------------------------------------------------------------------------
    def _receive(self) -> None:
        """Receiver thread: read messages and hand them to the event loop."""
        loop = self._loop
        assert loop is not None
        while not self._stop.is_set():
            conn = self.conn
            if conn is None:
                return
            try:
                conn.mav.robust_parsing = True
                msg = conn.recv_match(blocking=True, timeout=0.2)
            except Exception as exc:
                # pymavlink drops what it cannot decode; anything else (a TCP reset, a
                # serial port pulled) must not end the thread.
                if self._stop.is_set():
                    return
                self.bad_frames += 1
                logger.debug("mavlink: receive error: %s", exc)
                time.sleep(0.05)
                continue
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.bad_frames += 1
                continue
            if kind.startswith("UNKNOWN"):
                self.unknown_messages += 1
                continue
            try:
                loop.call_soon_threadsafe(self._deliver, msg)
            except RuntimeError:  # the loop is closed: we are shutting down
                return

    def _write(self) -> None:
        """Writer thread: send what the event loop queued (None stops it)."""
        while not self._stop.is_set():
            try:
                msg = self._out.get(timeout=0.5)
            except queue.Empty:
                continue
            if msg is None:
                return
            conn = self.conn
            if conn is None:
                return
            try:
                conn.mav.send(msg)
            except Exception as exc:  # a dropped TCP peer, a serial write timeout
                self.send_errors += 1
                logger.debug("mavlink: send failed: %s", exc)
                continue
            self._sent(msg)

    def _sent(self, msg: Any) -> None:
        """Hand a sent message's frame to :attr:`on_sent` on the event loop (its sink
        is not thread-safe). The frame is read after ``send``: pymavlink packs it then,
        with the sequence number and signature the autopilot got."""
        sink, loop = self.on_sent, self._loop
        if sink is None or loop is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
            loop.call_soon_threadsafe(sink, time.time(), bytes(msg.get_msgbuf()))

    def send(self, msg: Any) -> None:
        """Queue ``msg`` for the writer thread; never blocks (a full queue drops it)."""
        try:
            self._out.put_nowait(msg)
        except queue.Full:
            self.send_errors += 1
            logger.warning("mavlink: send queue full, message dropped")

    # --- receiving (event loop) ----------------------------------------------------------
    def _deliver(self, msg: Any) -> None:
        """Answers the link waits for, then the owner's turn. Never raises."""
        if self._stop.is_set():
            return  # read before the link closed: the autopilot is no longer ours to hear
        try:
            kind = msg.get_type()
            if (msg.get_srcSystem(), msg.get_srcComponent()) == self.target:
                if kind == "COMMAND_ACK":
                    self._on_ack(msg)
                elif kind == "STATUSTEXT":
                    self._on_text(msg)
                elif kind == "PARAM_VALUE":
                    for future in self._param_waiters.pop(param_name(msg.param_id), []):
                        if not future.done():
                            future.set_result(float(msg.param_value))
                for wanted, match, future in list(self._answer_waiters):
                    if kind in wanted and not future.done() and match(msg):
                        future.set_result(msg)
            self.on_message(msg)
        except Exception:
            logger.exception("mavlink: error handling %s", msg.get_type())

    def _on_ack(self, msg: Any) -> None:
        target_system = getattr(msg, "target_system", 0)
        if target_system not in (0, self.config.source_system):
            return  # an answer to another ground station on the same link
        pending = self._pending.get(int(msg.command))
        if pending is not None and not pending.future.done():
            pending.acked_at = time.monotonic()
            pending.future.set_result(msg)

    def _on_text(self, msg: Any) -> None:
        self.texts.append((time.monotonic(), int(msg.severity), statustext(msg)))

    def lost(self) -> None:
        """The autopilot went silent: whatever waits for an answer fails now."""
        for pending in self._pending.values():
            if not pending.future.done():
                pending.future.set_exception(self.lost_error(command_name(pending.command)))

    # --- commands ----------------------------------------------------------------------
    def lost_error(self, what: str) -> AdapterError:
        if self.conn is None:
            return AdapterError(
                f"the link to the autopilot is closed: {what} is refused", code="autopilot_lost"
            )
        return AdapterError(
            f"no heartbeat from the autopilot for over {self.config.heartbeat_timeout_s:g} s: "
            f"{what} is refused",
            code="autopilot_lost",
        )

    def require(self, what: str) -> None:
        """Raise AdapterError ``autopilot_lost`` unless the autopilot is heard."""
        if not self.ok:
            raise self.lost_error(what)

    def target_or_default(self) -> tuple[int, int]:
        cfg = self.config
        return self.target or (cfg.target_system or 1, cfg.target_component or 1)

    def boot_ms(self, since: float) -> int:
        """Milliseconds since ``since`` (monotonic) as MAVLink's uint32 time_boot_ms."""
        return int((time.monotonic() - since) * 1000) & 0xFFFFFFFF

    async def command_long(
        self,
        command: int,
        params: Sequence[float],
        *,
        ack_wait_s: float | None = None,
        label: str | None = None,
    ) -> Any:
        """COMMAND_LONG ``command`` with up to seven ``params``; returns the ACK."""
        p = list(params) + [0.0] * (7 - len(params))
        target = self.target_or_default()

        def build(confirmation: int) -> Any:
            return MAV.MAVLink_command_long_message(target[0], target[1], command, confirmation, *p)

        return await self._transact(command, build, ack_wait_s=ack_wait_s, label=label)

    async def command_int(
        self, command: int, frame: int, params: Sequence[float], lat: float, lon: float, z: float
    ) -> Any:
        """COMMAND_INT ``command`` at (lat, lon, z) in ``frame``; returns the ACK."""
        p = list(params) + [0.0] * (4 - len(params))
        target = self.target_or_default()

        def build(_: int) -> Any:
            return MAV.MAVLink_command_int_message(
                target[0], target[1], frame, command, 0, 0, *p,
                round(lat * 1e7), round(lon * 1e7), z,
            )  # fmt: skip

        return await self._transact(command, build, ack_wait_s=None, label=None)

    async def _transact(
        self,
        command: int,
        build: Callable[[int], Any],
        *,
        ack_wait_s: float | None,
        label: str | None,
    ) -> Any:
        """Send a command, resend it until its COMMAND_ACK, and turn the ACK into the
        agent's answer (see the module docstring)."""
        what = label or command_name(command)
        self.require(what)
        loop = asyncio.get_running_loop()
        timeout = self.config.command_timeout_s if ack_wait_s is None else ack_wait_s
        async with self._command_lock:
            started = time.monotonic()
            deadline = started + timeout
            pending = _Pending(command, loop.create_future(), started)
            self._pending[command] = pending
            confirmation = 0
            try:
                self.send(build(confirmation))
                sent_at = time.monotonic()
                while True:
                    wait = min(self.config.resend_s, deadline - time.monotonic())
                    try:
                        async with asyncio.timeout(max(0.01, wait)):
                            ack = await asyncio.shield(pending.future)
                    except TimeoutError:
                        if time.monotonic() >= deadline:
                            self.stats["timeouts"] += 1
                            raise AdapterError(
                                f"the autopilot did not answer {what} within {timeout:g} s",
                                code="timeout",
                            ) from None
                        # Lost on the way, or its ACK was: MAVLink resends with the
                        # confirmation counter raised.
                        confirmation = min(255, confirmation + 1)
                        self.send(build(confirmation))
                        sent_at = time.monotonic()
                        continue
                    if ack.result == MAV.MAV_RESULT_IN_PROGRESS:
                        pending.future = loop.create_future()
                        continue
                    break
            finally:
                self._pending.pop(command, None)
        self.stats["acks"] += 1
        if ack.result != MAV.MAV_RESULT_ACCEPTED:
            self.stats["refusals"] += 1
            raise AdapterError(
                self._refusal(what, int(ack.result), sent_at, pending.acked_at),
                code="autopilot_refused",
            )
        return ack

    def _refusal(self, what: str, result: int, sent_at: float, acked_at: float) -> str:
        """The refusal in words: the result, and the autopilot's explanation of it (see
        the module docstring) or, without one, what the result means."""
        words = RESULT_WORDS.get(result, f"result {result}")
        texts = [
            text
            for at, severity, text in self.texts
            if sent_at <= at <= acked_at and severity <= MAV.MAV_SEVERITY_WARNING
        ]
        reason = "; ".join(dict.fromkeys(texts[-2:])) or RESULT_HINTS.get(result, "")
        return f"autopilot refused {what}: {words}" + (f" ({reason})" if reason else "")

    # --- parameters --------------------------------------------------------------------
    async def read_param(self, name: str) -> float:
        """One autopilot parameter (PARAM_REQUEST_READ, resent until
        ``command_timeout_s``). Raises AdapterError ``timeout`` or ``autopilot_lost``."""
        self.require(f"reading {name}")
        loop = asyncio.get_running_loop()
        future: asyncio.Future[float] = loop.create_future()
        self._param_waiters.setdefault(name, []).append(future)
        target = self.target_or_default()
        deadline = time.monotonic() + self.config.command_timeout_s
        try:
            while True:
                self.send(
                    MAV.MAVLink_param_request_read_message(target[0], target[1], name.encode(), -1)
                )
                wait = min(self.config.resend_s, deadline - time.monotonic())
                try:
                    async with asyncio.timeout(max(0.01, wait)):
                        return await asyncio.shield(future)
                except TimeoutError:
                    if time.monotonic() >= deadline:
                        raise AdapterError(
                            f"the autopilot did not answer for parameter {name} within "
                            f"{self.config.command_timeout_s:g} s",
                            code="timeout",
                        ) from None
        finally:
            waiters = self._param_waiters.get(name, [])
            if future in waiters:
                waiters.remove(future)

    async def set_param(self, name: str, value: float) -> float:
        """PARAM_SET ``name`` to ``value``, resent until the autopilot echoes it in a
        PARAM_VALUE (ArduPilot's acknowledgement) within ``command_timeout_s``; returns
        the value it took. Raises AdapterError ``timeout`` (an autopilot without the
        parameter says nothing) or ``autopilot_lost``."""
        target = self.target_or_default()

        def build() -> Any:
            return MAV.MAVLink_param_set_message(
                target[0], target[1], name.encode(), float(value), MAV.MAV_PARAM_TYPE_REAL32
            )

        answer = await self.request(
            build,
            "PARAM_VALUE",
            lambda m: param_name(m.param_id) == name,
            what=f"setting {name}",
        )
        return float(answer.param_value)

    async def request(
        self,
        build: Callable[[], Any],
        answer: str | tuple[str, ...],
        match: Callable[[Any], bool],
        *,
        what: str,
        timeout_s: float | None = None,
    ) -> Any:
        """Send ``build()`` and resend it every ``resend_s`` until the autopilot's
        ``answer`` message (or one of several) for which ``match`` holds; returns it.
        Raises AdapterError ``timeout`` after ``timeout_s`` (``command_timeout_s``) or
        ``autopilot_lost``."""
        self.require(what)
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Any] = loop.create_future()
        waiter = ((answer,) if isinstance(answer, str) else answer, match, future)
        self._answer_waiters.append(waiter)
        timeout = self.config.command_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        try:
            while True:
                self.send(build())
                wait = min(self.config.resend_s, deadline - time.monotonic())
                try:
                    async with asyncio.timeout(max(0.01, wait)):
                        return await asyncio.shield(future)
                except TimeoutError:
                    if time.monotonic() >= deadline:
                        raise AdapterError(
                            f"the autopilot did not answer {what} within {timeout:g} s",
                            code="timeout",
                        ) from None
                    self.require(what)
        finally:
            self._answer_waiters.remove(waiter)
