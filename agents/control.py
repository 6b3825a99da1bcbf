"""Point-to-point control: users connect straight to the vehicle's agent.

:class:`ControlHub` holds the vehicle's current task and its connected users, whatever
carries their messages: a direct WebSocket (:class:`ControlServer`) or the platform's
relay. It

* admits a user only with a grant signed by the platform for this vehicle and the
  current task's session, each grant once (replays refused);
* gives control to one user at a time; the others watch. When control changes hands
  the adapter's inputs are zeroed first;
* runs every command through the :class:`~agents.safety.CommandGate` and answers each
  with an ``ack`` carrying its ``seq`` once the adapter applied or refused it; a
  movement the gate refuses at the ceiling or the geofence is stopped at once
  (:meth:`~agents.vehicles.base.Adapter.stop_motion`), not left to run its hold;
* streams telemetry per subscription at the requested rate, and answers pings;
* pings the controller to know the round trip (latency-aware limits) and watches its
  inputs: nothing within the task's link-loss timeout triggers the adapter's safe
  action and a ``failsafe`` event to the platform. A controller's socket closing (a
  page reloading, a tab closed) holds the vehicle neutral at once and gives the same
  user the rest of that timeout to come back: a page that reconnects in time takes
  the controls back without the fail-safe; one that comes back later is told, in its
  ``welcome``, the fail-safe the vehicle performed meanwhile (``vehicle.failsafe``);
* runs the commands of the task's autonomous mission (:mod:`agents.missions`) through
  :meth:`ControlHub.mission_execute`, under the same lock, and counts the user
  commands and fail-safes that take over from it (:attr:`ControlHub.overrides`);
* names the command in every refusal it acks, and folds a burst of refused commands
  into at most one ``command_refused`` report a second;
* reports a controller that went silent (fail-safe) and then speaks again on the same
  link (``link_recovered``);
* tells the controller what ending the session would make the vehicle do now
  (``consequence``: a drone landing goes on landing, whatever its fail-safe says);
* watches the vehicle's actual state against the task's limits while the task is
  current (:mod:`agents.envelope`): a breach is corrected under the same lock, takes
  over from a mission, and is reported (``envelope_breach``, ``envelope_restored``) to
  the platform and the users.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import re
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Coroutine, Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Final, Protocol, Self

import msgspec
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from agents.config import MAX_GRANT_LIFETIME_S
from agents.envelope import EnvelopeWatch
from agents.protocol import (
    MAX_MESSAGE_BYTES,
    ProtocolError,
    PublicKeys,
    ReplayGuard,
    UserGrant,
    VehicleTask,
    encode_message,
    error_message,
    parse_message,
)
from agents.protocol.messages import (
    Auth,
    ClientEvent,
    ClientPong,
    ClientWelcome,
    Command,
    CommandAck,
    CommandSpec,
    Keepalive,
    Message,
    Ping,
    Pong,
    ReleaseControl,
    RoleChange,
    Subscribe,
    TakeControl,
    Telemetry,
    Unsubscribe,
    VideoStatus,
    WebrtcAnswer,
    WebrtcOffer,
    message_type,
)
from agents.recording import NullRecorder, RecordSink, Source
from agents.safety import LIMIT_CODES, CommandGate, Refusal, plan_within
from agents.vehicles.base import SAFE_COMMANDS, Adapter, AdapterError, Breach
from agents.vehicles.plan import PlanItem

log = logging.getLogger(__name__)

#: Close codes (4000-4999 are the application's).
CLOSE_UNAUTHORIZED = 4401
CLOSE_FORBIDDEN = 4403
CLOSE_REPLACED = 4409
CLOSE_FLOOD = 4429

AUTH_TIMEOUT_S = 5.0
COMMAND_TIMEOUT_S = 10.0  # the adapter's own timeouts are shorter; this is a backstop
PING_INTERVAL_S = 0.5
#: Per-client message budget: a steady rate and a burst. Above it frames are refused,
#: and a client that keeps flooding is disconnected. Twice the paper's fastest control
#: rate (a command every 10 ms) plus keepalives fits comfortably.
RATE_PER_S = 200.0
BURST = 400.0
FLOOD_LIMIT = 300  # refused frames within FLOOD_WINDOW_S before disconnecting
FLOOD_WINDOW_S = 5.0
COMMAND_QUEUE = 16
#: Refused commands: the first of a burst is reported at once, the rest folded into at
#: most one report this often while they go on.
REFUSAL_REPORT_S = 1.0
#: A command older than this (or than the task's link-loss timeout, if longer) when its
#: turn comes is dropped: the user steered for a moment that has passed. Safe commands
#: are never dropped for age.
MIN_COMMAND_AGE_MS = 250.0
#: Clock samples kept per user; the one with the shortest round trip is trusted.
CLOCK_SAMPLES = 16
#: A user's WebRTC offers at most this often: each one builds a connection and gathers
#: candidates, far dearer than any other message.
OFFER_MIN_INTERVAL_S = 1.0

#: Messages that negotiate a WebRTC connection: only on the link the user signals on.
_SIGNALLING: Final = frozenset({WebrtcOffer})

Reporter = Callable[[str, str | None, dict[str, Any]], None]
TaskEnded = Callable[[VehicleTask], None]


def refusal_text(name: str, text: str) -> str:
    """``text`` as the user sees it in an ``ack``: naming the command ``name`` (a
    controller has several in flight), prefixed with it unless it already says it."""
    if re.search(rf"(?<!\w){re.escape(name)}(?!\w)", text):
        return text
    return f"{name}: {text}"


class _RefusalReports:
    """``command_refused`` reports for one hub, folded so a flooding controller cannot
    flood the platform: the first refusal of a burst is reported at once with data
    ``{name, code, reason, count: 1}``; while refusals go on, the next ones are
    summed into at most one report per REFUSAL_REPORT_S, with the last refusal's
    ``name``, ``code``, ``reason``, ``count`` (refusals since the previous report) and
    ``codes`` (code -> how many). :meth:`close` sends what is pending; after it nothing
    is reported for that session."""

    def __init__(self, report: Reporter) -> None:
        self.report = report
        self.session: str | None = None
        self.reported_at = -REFUSAL_REPORT_S
        self.count = 0
        self.codes: Counter[str] = Counter()
        self.last: dict[str, Any] = {}
        self.timer: asyncio.TimerHandle | None = None

    def add(self, session: str | None, name: str, code: str, reason: str) -> None:
        """One refused command of ``session`` (None: no task, not reported)."""
        if session is None:
            return
        if session != self.session:
            self.close()
            self.session = session
        now = time.monotonic()
        if self.count == 0 and now - self.reported_at >= REFUSAL_REPORT_S:
            self.reported_at = now
            self.report(
                "command_refused",
                session,
                {"name": name, "code": code, "reason": reason, "count": 1},
            )
            return
        self.count += 1
        self.codes[code] += 1
        self.last = {"name": name, "code": code, "reason": reason}
        if self.timer is None:
            delay = max(0.0, self.reported_at + REFUSAL_REPORT_S - now)
            self.timer = asyncio.get_running_loop().call_later(delay, self.flush)

    def flush(self) -> None:
        """Report the refusals pending, if any."""
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        if self.count and self.session is not None:
            self.report(
                "command_refused",
                self.session,
                {**self.last, "count": self.count, "codes": dict(self.codes)},
            )
            self.reported_at = time.monotonic()
        self.count = 0
        self.codes = Counter()

    def close(self) -> None:
        """The session ends: report what is pending, then nothing more for it."""
        self.flush()
        self.session = None


class ClientLink(Protocol):
    """One user's message channel: a WebSocket, a relayed connection, or a WebRTC data
    channel. ``path`` names it for the user and the platform (``websocket``, ``relay``;
    data channels take their ICE path, see :class:`_Paths`)."""

    id: str

    async def send(self, message: Message) -> None:
        """Send one control_to_client message; raises ConnectionError when gone."""

    async def close(self, code: int, reason: str) -> None:
        """Close the channel; idempotent."""


class _Paths:
    """One user's ClientLink over every path they have: the link they authenticated on
    (a direct WebSocket or the platform's relay, which also carries the WebRTC
    signalling) and, once open, the ``control`` data channel of the WebRTC connection
    they negotiated on it. Messages go on the data channel while it is open, else on
    the first link; the user stays connected while either is, so a platform outage
    leaves a WebRTC user in control and a failed WebRTC connection falls back to the
    relay without a new ``auth``."""

    def __init__(self, signal: ClientLink) -> None:
        self.id = signal.id
        self.signal: ClientLink | None = signal
        self.channel: ClientLink | None = None
        #: The ICE path of the WebRTC connection (``webrtc_direct``/``webrtc_turn``).
        self.rtc_path = "webrtc_direct"
        #: The path last announced to the user and the platform.
        self.announced: str | None = None

    @property
    def path(self) -> str:
        if self.channel is not None:
            return self.rtc_path
        return str(getattr(self.signal, "path", "websocket"))

    def carries(self, link: ClientLink) -> bool:
        """Is ``link`` one of this user's paths (or these paths themselves)?"""
        return link is self or link is self.signal or getattr(link, "id", None) == self.id

    async def send(self, message: Message) -> None:
        channel = self.channel
        if channel is not None:
            try:
                await channel.send(message)
                return
            except ConnectionError:
                pass  # the data channel just broke: the first link carries on
        if self.signal is None:
            raise ConnectionError("no path to the user is left")
        await self.signal.send(message)

    async def close(self, code: int, reason: str) -> None:
        for link in (self.channel, self.signal):
            if link is not None:
                with contextlib.suppress(Exception):
                    await link.close(code, reason)


class _Clock:
    """The user's clock against ours, from the ping exchange: each pong says what the
    user's clock read about half a round trip ago; the sample with the shortest round
    trip bounds the error best (NTP's rule)."""

    def __init__(self) -> None:
        self.samples: list[tuple[float, float]] = []  # (rtt_ms, offset_ms)

    def add(self, rtt_ms: float, client_ms: float) -> None:
        offset = client_ms - (time.time() * 1000.0 - rtt_ms / 2)
        self.samples = [*self.samples[-(CLOCK_SAMPLES - 1) :], (rtt_ms, offset)]

    def age_ms(self, client_ms: float) -> float | None:
        """How long ago, on our clock, the user's clock read ``client_ms``; None
        before any sample."""
        if not self.samples:
            return None
        offset = min(self.samples)[1]
        return time.time() * 1000.0 - (client_ms - offset)


@dataclass
class _Client:
    link: _Paths
    role: str = "pending"  # pending, controller, viewer
    grant: UserGrant | None = None
    rtt_ms: float | None = None
    clock: _Clock = field(default_factory=_Clock)
    offered_at: float = -OFFER_MIN_INTERVAL_S
    tokens: float = BURST
    refill_at: float = field(default_factory=time.monotonic)
    refused: list[float] = field(default_factory=list)
    telemetry: asyncio.Task[None] | None = None
    commands: asyncio.Queue[Command] = field(default_factory=lambda: asyncio.Queue(COMMAND_QUEUE))
    worker: asyncio.Task[None] | None = None
    #: The user's WebRTC offer being answered (ICE gathering), if any.
    offering: asyncio.Task[None] | None = None
    #: The words last sent of what ending the session would make the vehicle do.
    consequence: str | None = None
    #: The camera is on this user's WebRTC connection: told what it sends now.
    video: bool = False

    def allow(self) -> bool:
        """Token bucket: True when this frame is within the client's budget."""
        now = time.monotonic()
        self.tokens = min(BURST, self.tokens + (now - self.refill_at) * RATE_PER_S)
        self.refill_at = now
        if self.tokens >= 1:
            self.tokens -= 1
            return True
        self.refused = [t for t in self.refused if now - t < FLOOD_WINDOW_S]
        self.refused.append(now)
        return False

    @property
    def flooding(self) -> bool:
        return len(self.refused) >= FLOOD_LIMIT


class ControlHub:
    """The vehicle side of every user session; see the module docstring."""

    def __init__(
        self,
        *,
        vehicle_id: str,
        vehicle_name: str,
        public_key: PublicKeys,
        adapter: Adapter,
        report: Reporter,
        video: Any | None = None,
        on_task_end: TaskEnded | None = None,
        webrtc: Mapping[str, Any] | None = None,
        max_grant_lifetime_s: float = MAX_GRANT_LIFETIME_S,
        recorder: RecordSink | None = None,
    ) -> None:
        self.vehicle_id = vehicle_id
        #: The flight record: every command's outcome and every session's bounds.
        self.recorder: RecordSink = recorder or NullRecorder()
        #: A grant valid longer than this is refused (``lifetime_too_long``, agents.config).
        self.max_grant_lifetime_s = max_grant_lifetime_s
        self.vehicle_name = vehicle_name
        #: The platform key(s) grants are verified with; the agent replaces it when the
        #: platform announces new keys (a rotation).
        self.public_key = public_key
        self.adapter = adapter
        self.report = report
        self.video = video
        #: The agent's ``webrtc`` configuration (see agents.config); the peers are made
        #: on the first offer, so an agent nobody calls never loads aiortc.
        self.webrtc_options = dict(webrtc or {})
        self.rtc: Any | None = None
        self.task: VehicleTask | None = None
        self.gate: CommandGate | None = None
        self.clients: dict[str, _Client] = {}
        self.controller: _Client | None = None
        self.grants_seen = ReplayGuard()
        self.stats: dict[str, int] = {"commands": 0, "refused": 0, "failsafes": 0}
        # One command reaches the adapter at a time, and a fail-safe waits its turn.
        self._exec = asyncio.Lock()
        self._armed = False  # the watchdog runs once the controller has sent input
        self._last_input = 0.0
        self._watchdog: asyncio.Task[None] | None = None
        self._time_limit: asyncio.Task[None] | None = None
        self._pinger: asyncio.Task[None] | None = None
        self._background: set[asyncio.Future[None]] = set()
        self._envelope: EnvelopeWatch | None = None
        self._refusals = _RefusalReports(report)
        # The controller the watchdog found silent, and its last input before that.
        self._silenced: tuple[_Client, float] | None = None
        #: The fail-safe the vehicle performed on its own during the current task and
        #: that no controller's command has taken over since (cause, action, when: Unix
        #: seconds): a page that comes back is told (its ``welcome``).
        self.failsafe_done: dict[str, Any] | None = None
        #: Called with the task as it ends, before the safe action (stops its mission).
        self.on_task_end = on_task_end
        #: True while an autonomous mission flies the vehicle (set by its runner).
        self.autonomous = False
        #: User commands and fail-safes executed so far: a mission started at another
        #: count has been taken over (``override_reason`` says by what).
        self.overrides = 0
        self.override_reason = ""

    # --- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:
        self._watchdog = asyncio.create_task(self._watch(), name="control-watchdog")
        self._pinger = asyncio.create_task(self._ping_controller(), name="control-pinger")
        encoder = getattr(self.video, "encoder", None)
        if encoder is not None:  # the camera's size, rate and bitrate follow the link
            encoder.add_listener(self._video_status_changed)

    async def close(self) -> None:
        """Shut down: with a task current, the vehicle performs the task's fail-safe
        action first (the agent is stopping, SIGTERM or Ctrl-C: nobody will control the
        vehicle), then the users are dropped and everything stops."""
        await self._envelope_stop()
        current = self.task
        if current is not None:
            action = current.limits.failsafe_action
            log.warning("shutting down during session %s: %s", current.session_id, action)
            self._override(f"the agent's shutdown performed {action}")
            try:
                async with self._exec:
                    await self.adapter.safe_action(action)
            except Exception as exc:  # the rest of the shutdown must happen whatever
                log.exception("the shutdown's safe action %s failed", action)
                self._record_safe_action("failsafe", action, exc, cause="shutdown")
            else:
                log.warning("shutdown: %s under way", action)
                self._record_safe_action("failsafe", action, None, cause="shutdown")
        for client in list(self.clients.values()):
            await self._drop(client, 1001, "agent shutting down")
        encoder = getattr(self.video, "encoder", None)
        if encoder is not None:
            encoder.remove_listener(self._video_status_changed)
        if self.rtc is not None:
            await self.rtc.close()
        self._refusals.flush()
        if self._background:
            await asyncio.wait(self._background, timeout=2)
        for task in (self._watchdog, self._time_limit, self._pinger):
            if task:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    # --- tasks from the platform -------------------------------------------------------
    def task_accept(self, task: VehicleTask) -> None:
        """Make ``task`` current. Raises Refusal("busy") while another session runs."""
        if self.task is not None and self.task.session_id != task.session_id:
            raise Refusal("busy", f"the vehicle is serving session {self.task.session_id}")
        if self.task is None:
            self.failsafe_done = None
        self.task = task
        self.recorder.session_start(task.session_id)
        watch = EnvelopeWatch(
            limits=task.limits,
            state=self.adapter.state,
            recover=self._envelope_recover,
            notify=self._envelope_notify,
            braking=self.adapter.braking,
        )
        self.gate = CommandGate(
            self.adapter,
            allowed=task.allowed_commands,
            limits=task.limits,
            breached=lambda: watch.envelope.breached,
        )
        # The watch of the previous copy of this task (the platform resent it) goes.
        previous, self._envelope = self._envelope, watch
        self._envelope.start()
        if previous is not None:
            self._spawn(previous.stop())
        if self._time_limit:
            self._time_limit.cancel()
        limit = task.limits.session_time_limit_s
        if limit:
            self._time_limit = asyncio.create_task(self._expire(task.session_id, limit))

    async def task_end(self, session_id: str, *, reason: str, action: str | None) -> bool:
        """End the current task if it is ``session_id``: users are told and dropped, the
        vehicle performs ``action`` (default: the task's fail-safe). False if not current."""
        task = self.task
        if task is None or task.session_id != session_id:
            return False
        self.task = None
        self.gate = None
        self._armed = False
        # Before the safe action: the envelope must not correct what the end performs.
        await self._envelope_stop()
        if self.on_task_end is not None:
            try:
                self.on_task_end(task)
            except Exception:  # the safe action below must happen whatever
                log.exception("on_task_end failed")
        for client in list(self.clients.values()):
            with contextlib.suppress(ConnectionError):
                await client.link.send(ClientEvent(event="session_ended", data={"reason": reason}))
            await self._drop(client, CLOSE_FORBIDDEN, reason[:120])
        safe = action or task.limits.failsafe_action
        try:
            async with self._exec:
                await self.adapter.safe_action(safe)
        except Exception as exc:
            self._record_safe_action("platform", safe, exc, cause=reason)
            raise
        self._record_safe_action("platform", safe, None, cause=reason)
        self._refusals.close()  # the platform hears them before the end, never after
        self.report("task_ended", session_id, {"reason": reason})
        self.recorder.session_end()
        return True

    async def _expire(self, session_id: str, limit_s: float) -> None:
        await asyncio.sleep(limit_s)
        await self.task_end(session_id, reason="session time limit reached", action=None)

    async def mission_execute(
        self, session_id: str, name: str, args: Mapping[str, Any], *, epoch: int
    ) -> None:
        """Run one command of the current task's autonomous mission.

        The mission is the platform's own signed plan, so the task's allowed commands
        (what *users* may send) do not apply; everything else does: the vocabulary and
        argument checks, the ceiling and the geofence. It runs under the same lock as
        users' commands and fail-safes, and only if, once the lock is held,
        ``session_id`` is still the current task and :attr:`overrides` still equals
        ``epoch`` (the count the mission started from): a mission step queued behind a
        fail-safe or the end-of-task safe action never undoes it.

        Raises Refusal (``no_task``, ``overridden``, ``unknown_command``, ``bad_args``,
        ``altitude_limit``, ``geofence``) or AdapterError (``timeout`` after
        COMMAND_TIMEOUT_S, or the adapter's own).
        """
        async with self._exec:
            task = self.task
            if task is None or task.session_id != session_id:
                raise Refusal("no_task", "the mission's session is not the vehicle's task now")
            if self.overrides != epoch:
                raise Refusal("overridden", self.override_reason or "someone else took over")
            vocabulary = tuple(c.name for c in self.adapter.commands())
            gate = CommandGate(self.adapter, allowed=vocabulary, limits=task.limits)
            try:
                checked = gate.check(name, args)
                try:
                    # Not asyncio.wait_for: on Python 3.11 it swallows a cancellation
                    # that arrives as the command completes, and a cancelled (replaced,
                    # ended) mission would then fly on.
                    async with asyncio.timeout(COMMAND_TIMEOUT_S):
                        await self.adapter.execute(checked.name, checked.args)
                except TimeoutError:
                    raise AdapterError(
                        f"{name} got no answer from the vehicle", code="timeout"
                    ) from None
            except (Refusal, AdapterError) as exc:
                self.recorder.command(
                    source="mission", name=name, args=args, ok=False, code=exc.code, error=str(exc)
                )
                raise
            self.recorder.command(source="mission", name=name, args=args, ok=True)

    async def mission_native_upload(
        self, session_id: str, items: Sequence[PlanItem], *, epoch: int
    ) -> None:
        """Hand the current task's mission to the vehicle's own engine (see
        :mod:`agents.vehicles.plan`), as :meth:`mission_execute` runs a command: under
        the same lock, only while ``session_id`` is the task and ``epoch`` still holds.
        The autopilot will fly it without asking again, so the whole plan is checked
        now: every waypoint inside the task's ceiling and geofence, every speed at most
        the task's maximum (a faster one is lowered to it).

        Raises Refusal (``no_task``, ``overridden``, ``altitude_limit``, ``geofence``,
        ``unknown_command`` when the vehicle has no engine) or AdapterError (the
        autopilot's refusal, ``timeout``)."""
        async with self._exec:
            task = self._mission_task(session_id, epoch)
            engine = self.adapter.native_missions()
            if engine is None:
                raise Refusal("unknown_command", "this vehicle flies no mission of its own")
            checked = plan_within(items, task.limits)
            # An upload is one round trip per item: its own time, beyond a command's.
            try:
                async with asyncio.timeout(COMMAND_TIMEOUT_S + len(items)):
                    await engine.mission_upload(checked)
            except TimeoutError:
                raise AdapterError("the mission upload got no answer", code="timeout") from None
            except (Refusal, AdapterError) as exc:
                self.recorder.command(
                    source="mission", name="mission_upload", args={"items": len(items)},
                    ok=False, code=exc.code, error=str(exc),
                )  # fmt: skip
                raise
            self.recorder.command(
                source="mission", name="mission_upload", args={"items": len(items)}, ok=True
            )

    async def mission_native_adopt(
        self, session_id: str, items: Sequence[PlanItem], *, epoch: int
    ) -> bool:
        """Whether the vehicle's own engine flies the current task's mission already
        (this agent restarted while it flew): :meth:`mission_native_upload`'s plan, as
        it would have handed it over, is compared with what the engine flies; when they
        agree, the engine's mission is followed from where it is and nothing is handed
        over again (see :meth:`NativeMissions.mission_adopt`). Same checks and lock as
        :meth:`mission_native_upload`. False when the engine flies nothing or something
        else, or cannot say (logged): the mission is then handed over as usual."""
        async with self._exec:
            task = self._mission_task(session_id, epoch)
            engine = self.adapter.native_missions()
            if engine is None:
                return False
            checked = plan_within(items, task.limits)
            try:
                # Reading the mission back is one round trip per item, as an upload.
                async with asyncio.timeout(COMMAND_TIMEOUT_S + len(items)):
                    adopted = await engine.mission_adopt(checked)
            except (TimeoutError, AdapterError) as exc:
                log.warning("the vehicle's mission could not be read back: %s", exc)
                return False
            if adopted:
                self.recorder.command(
                    source="mission", name="mission_adopt", args={"items": len(items)}, ok=True
                )
            return adopted

    async def mission_native_start(self, session_id: str, *, epoch: int) -> None:
        """Start the mission :meth:`mission_native_upload` handed over (same checks and
        lock). Raises Refusal or AdapterError as it does."""
        async with self._exec:
            self._mission_task(session_id, epoch)
            engine = self.adapter.native_missions()
            if engine is None:
                raise Refusal("unknown_command", "this vehicle flies no mission of its own")
            try:
                async with asyncio.timeout(COMMAND_TIMEOUT_S):
                    await engine.mission_start()
            except TimeoutError:
                raise AdapterError("mission_start got no answer", code="timeout") from None
            except AdapterError as exc:
                self.recorder.command(
                    source="mission", name="mission_start", args={}, ok=False,
                    code=exc.code, error=str(exc),
                )  # fmt: skip
                raise
            self.recorder.command(source="mission", name="mission_start", args={}, ok=True)

    def _mission_task(self, session_id: str, epoch: int) -> VehicleTask:
        """The current task, if it is the mission's and nobody took over since."""
        task = self.task
        if task is None or task.session_id != session_id:
            raise Refusal("no_task", "the mission's session is not the vehicle's task now")
        if self.overrides != epoch:
            raise Refusal("overridden", self.override_reason or "someone else took over")
        return task

    def _override(self, reason: str) -> None:
        """A user command, a fail-safe or the envelope acted on the vehicle: a mission
        must yield."""
        self.overrides += 1
        self.override_reason = reason

    # --- the envelope ------------------------------------------------------------------
    async def _envelope_recover(self, breach: Breach) -> str:
        """Correct a breach, under the command lock like any command: never in the
        middle of a user's command or a mission step, and a mission yields to it."""
        async with self._exec:
            if self.task is None:
                return "none: the task has ended"
            try:
                async with asyncio.timeout(COMMAND_TIMEOUT_S):
                    action = await self.adapter.envelope_recover(breach)
                self.recorder.command(
                    source="safety",
                    name="envelope_recover",
                    args={"limit": breach.limit, "action": action},
                    ok=True,
                )
            except Exception as exc:
                self.recorder.command(
                    source="safety",
                    name="envelope_recover",
                    args={"limit": breach.limit},
                    ok=False,
                    code=getattr(exc, "code", type(exc).__name__),
                    error=str(exc),
                )
                raise
            finally:
                # Counted before the lock is free, whatever happened: the vehicle may
                # have been moved, and a mission step must not fly on regardless.
                self._override(f"the safety envelope ({breach.limit} limit)")
        return action

    async def _envelope_notify(self, event: str, data: dict[str, Any]) -> None:
        task = self.task
        if task is None:
            return
        self.report(event, task.session_id, data)
        for client in list(self.clients.values()):
            if client.role != "pending":
                await self._send(client, ClientEvent(event=event, data=data))

    async def _envelope_stop(self) -> None:
        watch, self._envelope = self._envelope, None
        if watch is not None:
            await watch.stop()

    # --- connections -------------------------------------------------------------------
    async def connected(self, link: ClientLink) -> None:
        """A user's channel opened; it must authenticate within AUTH_TIMEOUT_S."""
        client = _Client(_Paths(link))
        self.clients[link.id] = client
        asyncio.get_running_loop().call_later(AUTH_TIMEOUT_S, self._auth_deadline, client)

    def _auth_deadline(self, client: _Client) -> None:
        if client.role == "pending" and self.clients.get(client.link.id) is client:
            self._spawn(self._drop(client, CLOSE_UNAUTHORIZED, "no auth in time"))

    async def disconnected(self, link: ClientLink) -> None:
        """A user's channel closed (or was dropped). While their WebRTC data channel is
        open, losing the link they signalled on only loses that path."""
        client = self.clients.get(link.id)
        if client is None or not client.link.carries(link):
            return
        paths = client.link
        if link is paths.signal and paths.channel is not None:
            paths.signal = None
            await self._path_announce(client)
            return
        del self.clients[link.id]
        self._stop_client_tasks(client)
        if self.rtc is not None:
            with contextlib.suppress(Exception):
                await self.rtc.close_peer(link.id, notify=False)
        if client.grant is not None and self.task is not None:
            self.report(
                "user_disconnected",
                self.task.session_id,
                {"user": client.grant.user, "role": client.role},
            )
        if self._silenced is not None and self._silenced[0] is client:
            self._silenced = None
        if client is self.controller:
            self.controller = None
            # The controller's socket is gone (a page reloading, a tab closed, a network
            # that dropped): the vehicle stops what the user's keys were doing now, and
            # the watchdog (still armed) performs the fail-safe once the link-loss
            # timeout has passed since their last input, unless the same user's page
            # connects again first (_auth: it takes over).
            if self._armed and not self.autonomous:
                try:
                    async with self._exec:
                        await self.adapter.neutral()
                except Exception:  # the watchdog's fail-safe still comes
                    log.exception("holding the vehicle neutral failed")
            # The same user's other page, connected meanwhile (a reload whose new page
            # authenticated before the old socket's close arrived), takes over.
            heir = next(
                (
                    other
                    for other in self.clients.values()
                    if other.role == "viewer"
                    and other.grant is not None
                    and self.task is not None
                    and other.grant.role == "controller"
                    and other.grant.user == self.task.user
                ),
                None,
            )
            if heir is not None:
                await self._set_controller(heir)
                await self._send(heir, RoleChange(role="controller"))

    async def received(self, link: ClientLink, raw: str | bytes | Message) -> None:
        """Handle one frame from a user: its text, or the message struct already parsed
        from it (a relayed frame, parsed with the uplink message that carried it). Never
        raises for anything the user sent."""
        client = self.clients.get(link.id)
        if client is None:
            return
        if not client.allow():
            if client.flooding:
                await self._drop(client, CLOSE_FLOOD, "too many messages")
            else:
                await self._send(client, error_message("rate_limited", "slow down"))
            return
        try:
            msg = (
                raw if isinstance(raw, Message) else parse_message(raw, channel="control_to_agent")
            )
        except ProtocolError as exc:
            await self._send(client, error_message(exc.code, exc.message))
            if client.role == "pending":
                await self._drop(client, CLOSE_UNAUTHORIZED, "authenticate first")
            return
        if client.role == "pending":
            if not isinstance(msg, Auth):
                await self._send(client, error_message("unauthorized", "authenticate first"))
                await self._drop(client, CLOSE_UNAUTHORIZED, "authenticate first")
                return
            await self._auth(client, msg.grant)
            return
        handler = self._handlers.get(type(msg))
        if handler is None or (
            type(msg) in _SIGNALLING and link is not client.link.signal and link is not client.link
        ):
            # Signalling on a data channel would replace the connection carrying it.
            kind = message_type(msg)
            await self._send(client, error_message("unexpected", f"{kind} is not expected now"))
            return
        with contextlib.suppress(ConnectionError):
            await handler(self, client, msg)

    # --- authentication and roles ------------------------------------------------------
    async def _auth(self, client: _Client, token: str) -> None:
        try:
            grant = UserGrant.verify(
                token,
                self.public_key,
                vehicle_id=self.vehicle_id,
                replay_guard=self.grants_seen,
                max_lifetime_s=self.max_grant_lifetime_s,
            )
        except ProtocolError as exc:
            await self._send(client, error_message(exc.code, exc.message))
            await self._drop(client, CLOSE_UNAUTHORIZED, exc.code)
            return
        task = self.task
        if task is None or grant.session_id != task.session_id:
            await self._send(
                client, error_message("no_task", "this grant is not for the vehicle's current task")
            )
            await self._drop(client, CLOSE_FORBIDDEN, "no such session here")
            return
        client.grant = grant
        wants_control = grant.role == "controller" and grant.user == task.user
        failsafe = self.failsafe_done
        # The controller's link went silent and the fail-safe acted, its socket still
        # counted open here (a relay cut with its platform process, a network that
        # dropped without a close): the user's new connection takes the controls.
        silent = self.controller is not None and (
            self._silenced is not None and self._silenced[0] is self.controller
        )
        if wants_control and self.controller is None:
            # Back within the link-loss timeout (a reload): the watchdog is disarmed
            # before it fires, and the user drives on.
            await self._set_controller(client)
        elif wants_control and silent:
            await self._hand_over(client, task)
        else:
            client.role = "viewer"
        vehicle: dict[str, Any] = {
            "id": self.vehicle_id,
            "name": self.vehicle_name,
            "adapter": self.adapter.name,
            "session_id": task.session_id,
            "link_loss_timeout_ms": task.limits.link_loss_timeout_ms,
            "video": self.video is not None,
            # What each fail-safe action does to this vehicle, in words ("climb to its
            # return altitude, fly back to its home point and land").
            "safe_actions": dict(self.adapter.safe_action_words),
            "consequence": self._consequence(task),
        }
        if failsafe is not None:
            vehicle["failsafe"] = {**failsafe, "ago_s": round(time.time() - failsafe["at"], 1)}
        await self._send(
            client,
            ClientWelcome(
                role=client.role,  # type: ignore[arg-type]  # controller or viewer by now
                vehicle=vehicle,
                commands=[
                    msgspec.convert(
                        {
                            **c.to_profile(),
                            "allowed": c.name in task.allowed_commands or c.name in SAFE_COMMANDS,
                        },
                        CommandSpec,
                    )
                    for c in self.adapter.commands()
                ],
                telemetry=self.adapter.telemetry_topics(),
                telemetry_info=self.adapter.telemetry_info(),
            ),
        )
        self.report("user_connected", task.session_id, {"user": grant.user, "role": client.role})
        await self._path_announce(client)

    async def _set_controller(self, client: _Client | None) -> None:
        if self.controller is not None and self.controller is not client:
            previous = self.controller
            previous.role = "viewer"
            with contextlib.suppress(ConnectionError):
                await previous.link.send(RoleChange(role="viewer"))
        # Whoever held the sticks, the new holder starts from neutral; not while a
        # mission flies: zeroing the inputs would stop it mid-leg (a rescue user's page
        # joining as controller), and a user who really steers takes over anyway.
        if not self.autonomous:
            async with self._exec:
                await self.adapter.neutral()
        self._armed = False
        self._silenced = None
        self.controller = client
        if client is not None:
            client.role = "controller"
            client.worker = asyncio.create_task(self._run_commands(client))

    # --- message handlers --------------------------------------------------------------
    async def _on_command(self, client: _Client, msg: Command) -> None:
        name = msg.name
        if client is not self.controller:
            await self._ack(
                client, msg, "view_only", f"{name}: you are watching; take control first"
            )
            return
        await self._heard(client)
        if name in SAFE_COMMANDS:
            # A stop must not wait behind the moves queued before it: they are dropped
            # (each acked ``superseded``) and the stop runs next.
            while not client.commands.empty():
                dropped = client.commands.get_nowait()
                await self._ack(
                    client, dropped, "superseded", f"{dropped.name}: superseded by {name}"
                )
        try:
            client.commands.put_nowait(msg)
        except asyncio.QueueFull:
            await self._ack(
                client, msg, "busy", f"{name}: commands are arriving faster than applied"
            )

    async def _run_commands(self, client: _Client) -> None:
        """Apply the controller's commands in order, one at a time."""
        while True:
            msg = await client.commands.get()
            seq, name, args = msg.seq, msg.name, msg.args
            if client is not self.controller or self.gate is None or self.task is None:
                await self._ack(client, msg, "view_only", f"{name}: you no longer hold control")
                continue
            late = self._too_old(client, msg)
            if late is not None:
                await self._ack(client, msg, "stale", late)
                continue
            try:
                checked = self.gate.check(name, args, rtt_ms=client.rtt_ms)
                async with self._exec:
                    async with asyncio.timeout(COMMAND_TIMEOUT_S):
                        await self.adapter.execute(checked.name, checked.args)
                    # Counted before the lock is free: a mission step waiting for it
                    # sees that the user took over.
                    self._override(f"the user sent {name}")
            except (Refusal, AdapterError) as exc:
                if isinstance(exc, Refusal) and exc.code in LIMIT_CODES.values():
                    await self._stop_motion(name)
                self.stats["refused"] += 1
                reason = refusal_text(name, str(exc))
                await self._ack(client, msg, exc.code, reason)
                self._refusals.add(
                    self.task.session_id if self.task else None, name, exc.code, reason
                )
                continue
            except TimeoutError:
                await self._ack(client, msg, "timeout", f"{name} got no answer from the vehicle")
                continue
            self.stats["commands"] += 1
            self.failsafe_done = None  # the user has the vehicle again
            self._input()
            self._record_command(client, msg, ok=True)
            with contextlib.suppress(ConnectionError):
                await client.link.send(CommandAck(seq=seq, ok=True, error=None))

    async def _stop_motion(self, name: str) -> None:
        """A movement refused at a limit: the one it repeats must not run its hold out
        (a climb refused at the ceiling stops now, under the command lock)."""
        gate = self.gate
        if gate is None or not gate.is_motion(name):
            return
        async with self._exec:
            try:
                await self.adapter.stop_motion(name)
            except Exception:  # the refusal is acked whatever happened here
                log.exception("stopping %s at a limit failed", name)

    def _too_old(self, client: _Client, msg: Command) -> str | None:
        """Why ``msg`` is too old to run now, or None (fresh, safe, or its age unknown)."""
        if not isinstance(msg.t, float | int) or msg.name in SAFE_COMMANDS or self.task is None:
            return None
        age = client.clock.age_ms(float(msg.t))
        bound = max(MIN_COMMAND_AGE_MS, float(self.task.limits.link_loss_timeout_ms))
        if age is None or age <= bound:
            return None
        return f"{msg.name}: sent {age:.0f} ms ago, older than the {bound:.0f} ms allowed; dropped"

    async def _on_keepalive(self, client: _Client, msg: Keepalive) -> None:
        if client is self.controller:
            await self._heard(client)

    async def _on_ping(self, client: _Client, msg: Ping) -> None:
        # Pings measure the link; only commands and keepalives show a user in control.
        await self._send(client, ClientPong(t=msg.t, server_t=time.time()))

    async def _on_pong(self, client: _Client, msg: Pong) -> None:
        sent = msg.t
        now = time.monotonic()
        if 0 <= now - sent < 60:  # our own monotonic stamp echoed back
            client.rtt_ms = (now - sent) * 1000.0
            if isinstance(msg.client_t, float | int):
                client.clock.add(client.rtt_ms, float(msg.client_t))

    async def _on_subscribe(self, client: _Client, msg: Subscribe) -> None:
        topics = list(dict.fromkeys(msg.topics))
        known = set(self.adapter.telemetry_topics())
        unknown = [t for t in topics if t not in known]
        if unknown:
            await self._send(
                client,
                error_message("unknown_topic", f"unknown telemetry topic(s): {', '.join(unknown)}"),
            )
            return
        if client.telemetry:
            client.telemetry.cancel()
        client.telemetry = asyncio.create_task(self._stream(client, topics, msg.rate_hz))

    async def _on_unsubscribe(self, client: _Client, msg: Unsubscribe) -> None:
        if client.telemetry:
            client.telemetry.cancel()
            client.telemetry = None

    async def _on_take_control(self, client: _Client, msg: TakeControl) -> None:
        task = self.task
        if (
            client.grant is None
            or task is None
            or client.grant.role != "controller"
            or (client.grant.user != task.user)
        ):
            await self._send(client, error_message("view_only", "your grant is view-only"))
            return
        if client is not self.controller:
            await self._hand_over(client, task)
        await self._send(client, RoleChange(role="controller"))

    async def _hand_over(self, client: _Client, task: VehicleTask) -> None:
        """``client`` (the session's user) takes the controls. The platform follows who
        holds the sticks: a hand-over between the user's devices, control taken up
        again after the controller left, or from a controller gone silent."""
        previous = self.controller
        await self._set_controller(client)
        self.report(
            "control_handover",
            task.session_id,
            {
                "user": client.grant.user if client.grant is not None else None,
                "from": previous.link.id if previous is not None else None,
                "to": client.link.id,
                "role": "controller",
            },
        )

    async def _on_release_control(self, client: _Client, msg: ReleaseControl) -> None:
        if client is self.controller:
            await self._set_controller(None)
            client.role = "viewer"
            if self.task is not None and client.grant is not None:
                self.report(
                    "control_released",
                    self.task.session_id,
                    {"user": client.grant.user, "from": client.link.id, "role": "controller"},
                )
        viewer = client.role == "viewer"
        await self._send(client, RoleChange(role="viewer" if viewer else "controller"))

    async def _on_webrtc_offer(self, client: _Client, msg: WebrtcOffer) -> None:
        """The browser's offer: one connection for its data channels and the camera
        (:mod:`agents.rtc`), with the ICE servers the platform sent along."""
        now = time.monotonic()
        if now - client.offered_at < OFFER_MIN_INTERVAL_S:
            await self._send(
                client, error_message("rate_limited", "one WebRTC offer a second at most")
            )
            return
        client.offered_at = now
        rtc = self._rtc()
        if rtc is None:
            await self._send(
                client, error_message("no_webrtc", "this vehicle does not accept WebRTC")
            )
            return
        # Answered in a task of its own: the answer waits for every ICE candidate (no
        # trickle), up to aioice's 5 s for a STUN or TURN server that does not answer,
        # and the reader that called us carries the user's commands and pings (on the
        # relay, every user's and the platform's messages): none of them may wait.
        if client.offering is not None:
            client.offering.cancel()  # superseded by this one
        client.offering = asyncio.create_task(self._answer_offer(client, rtc, msg.sdp))

    async def _answer_offer(self, client: _Client, rtc: Any, sdp: str) -> None:
        servers = getattr(client.link.signal, "ice_servers", ())
        try:
            answer = await rtc.accept(
                client.link.id,
                sdp,
                ice_servers=servers,
                controller=client.grant is not None and client.grant.role == "controller",
            )
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # any WebRTC failure is reported to the user, not fatal
            await self._send(client, error_message("webrtc", str(exc)))
            return
        await self._send(client, WebrtcAnswer(sdp=answer))
        if "\nm=video " in sdp:
            client.video = True
            status = getattr(getattr(self.video, "encoder", None), "status", None)
            if status is not None:  # the stream already runs for someone else
                await self._send(client, _video_status_message(status))

    def _video_status_changed(self, status: Any) -> None:
        """The camera's encoder changed size, frame rate or bitrate (a
        :class:`agents.video.encoder.VideoStatus`): tell every user who watches it directly."""
        message = _video_status_message(status)
        for client in list(self.clients.values()):
            if client.video:
                self._spawn(self._send(client, message))

    # --- WebRTC paths (agents.rtc.PeerEvents) ---------------------------------------------
    def _rtc(self) -> Any | None:
        if self.rtc is None and self.webrtc_options.get("enabled", True):
            from agents.rtc import RtcPeers  # aiortc loads only when someone calls

            options = {k: v for k, v in self.webrtc_options.items() if k != "enabled"}
            self.rtc = RtcPeers(self, video=self.video, **options)
        return self.rtc

    async def channel_opened(self, peer_id: str, link: ClientLink) -> None:
        """A user's ``control`` data channel opened: their messages now use it."""
        client = self.clients.get(peer_id)
        if client is None:
            await link.close(CLOSE_FORBIDDEN, "no such user")
            return
        client.link.channel = link
        await self._path_announce(client)

    async def path_changed(self, peer_id: str, path: str) -> None:
        """ICE chose the pair of a user's connection (direct or through TURN)."""
        client = self.clients.get(peer_id)
        if client is not None:
            client.link.rtc_path = path
            await self._path_announce(client)

    async def channel_closed(self, peer_id: str) -> None:
        """A user's WebRTC connection ended: back on the link they signalled on, or, if
        that is gone too, disconnected."""
        client = self.clients.get(peer_id)
        if client is None or client.link.channel is None:
            return
        client.link.channel = None
        if client.link.signal is None:
            await self.disconnected(client.link)
        else:
            await self._path_announce(client)

    async def _path_announce(self, client: _Client) -> None:
        """Tell the user (``event path``) and the platform (``control_path``) which path
        their messages take, when it changed."""
        path = client.link.path
        if path == client.link.announced or client.role == "pending":
            return
        client.link.announced = path
        await self._send(client, ClientEvent(event="path", data={"path": path}))
        if self.task is not None and client.grant is not None:
            self.report(
                "control_path",
                self.task.session_id,
                {"user": client.grant.user, "role": client.role, "path": path},
            )

    # Each handler takes the struct of its key (typed per handler, hence Any here).
    _handlers: dict[type[Message], Callable[[ControlHub, _Client, Any], Awaitable[None]]] = {
        Command: _on_command,
        Keepalive: _on_keepalive,
        Ping: _on_ping,
        Pong: _on_pong,
        Subscribe: _on_subscribe,
        Unsubscribe: _on_unsubscribe,
        TakeControl: _on_take_control,
        ReleaseControl: _on_release_control,
        WebrtcOffer: _on_webrtc_offer,
    }

    # --- background loops --------------------------------------------------------------
    async def _stream(self, client: _Client, topics: list[str], rate_hz: float) -> None:
        period = 1.0 / rate_hz
        next_at = time.monotonic()
        while True:
            values = self.adapter.telemetry()
            try:
                await client.link.send(
                    Telemetry(t=time.time(), data={t: values.get(t) for t in topics})
                )
            except ConnectionError:
                # A path broke under a user who is still here (the uplink carrying their
                # relay reconnected, a data channel closed): the next sample goes on
                # whatever path they have then. Gone for good, they leave the clients
                # and their stream is cancelled with them.
                if self.clients.get(client.link.id) is not client:
                    return
            # Keep the rate even when a send was slow, without bursting to catch up.
            next_at = max(next_at + period, time.monotonic())
            await asyncio.sleep(next_at - time.monotonic())

    def _consequence(self, task: VehicleTask) -> dict[str, str]:
        """What ending ``task`` would make the vehicle do now: its end's action (the
        task's fail-safe) and the words for it, as the vehicle stands."""
        action = task.limits.failsafe_action
        words = self.adapter.safe_action_now(action) or self.adapter.safe_action_words.get(
            action, action.replace("_", " ")
        )
        return {"action": action, "words": words}

    async def _ping_controller(self) -> None:
        while True:
            await asyncio.sleep(PING_INTERVAL_S)
            client, task = self.controller, self.task
            if client is None:
                continue
            with contextlib.suppress(ConnectionError):
                await client.link.send(Ping(t=time.monotonic()))
                if task is not None:
                    # What ending the session would do changes as the vehicle flies
                    # (landing, on the ground): the page's confirmation says it as it is.
                    now = self._consequence(task)
                    if now["words"] != client.consequence:
                        client.consequence = now["words"]
                        await client.link.send(ClientEvent(event="consequence", data=now))

    async def _watch(self) -> None:
        while True:
            timeout_s = (self.task.limits.link_loss_timeout_ms if self.task else 500) / 1000
            await asyncio.sleep(min(0.05, timeout_s / 5))
            if self._armed and time.monotonic() - self._last_input > timeout_s:
                # Silence, with the socket still open: if this controller speaks again
                # on it, the platform hears that the link came back.
                if self.controller is not None:
                    self._silenced = (self.controller, self._last_input)
                await self._failsafe("link_lost")

    def _input(self) -> None:
        self._last_input = time.monotonic()
        self._armed = True

    async def _heard(self, client: _Client) -> None:
        """The controller sent input (a command or a keepalive)."""
        silenced = self._silenced
        if silenced is not None and silenced[0] is client:
            self._silenced = None
            after_ms = round((time.monotonic() - silenced[1]) * 1000)
            data = {"user": client.grant.user if client.grant else None, "after_ms": after_ms}
            log.warning("controller back after %d ms of silence", after_ms)
            if self.task is not None:
                self.report("link_recovered", self.task.session_id, data)
            await self._send(client, ClientEvent(event="link_recovered", data=data))
        self._input()

    async def _failsafe(self, cause: str) -> None:
        """The controller went quiet or away: make the vehicle safe and tell everyone."""
        self._armed = False
        task = self.task
        action = task.limits.failsafe_action if task else "stop"
        self.stats["failsafes"] += 1
        self._override(f"the fail-safe ({cause}) performed {action}")
        try:
            async with self._exec:
                await self.adapter.safe_action(action)
        except Exception as exc:
            # The watchdog must survive an adapter bug: report it and keep watching.
            log.exception("fail-safe %s failed", action)
            self._record_safe_action("failsafe", action, exc, cause=cause)
            self.report("safe_action_failed", task.session_id if task else None, {"action": action})
        else:
            self._record_safe_action("failsafe", action, None, cause=cause)
        log.warning("fail-safe: %s -> %s", cause, action)
        self.failsafe_done = {"cause": cause, "action": action, "at": time.time()}
        for client in list(self.clients.values()):
            with contextlib.suppress(ConnectionError):
                await client.link.send(
                    ClientEvent(event="failsafe", data={"cause": cause, "action": action})
                )
        self.report(
            "failsafe", task.session_id if task else None, {"cause": cause, "action": action}
        )

    # --- helpers -----------------------------------------------------------------------
    async def _ack(self, client: _Client, msg: Command, code: str, error: str) -> None:
        """Refuse the user's command ``msg`` (its ``ack``), and record that."""
        self._record_command(client, msg, ok=False, code=code, error=error)
        with contextlib.suppress(ConnectionError):
            await client.link.send(CommandAck(seq=msg.seq, ok=False, error=error, code=code))

    def _record_command(
        self,
        client: _Client,
        msg: Command,
        *,
        ok: bool,
        code: str | None = None,
        error: str | None = None,
    ) -> None:
        """A user's command and its acknowledgement go into the flight record, with its
        age when it carried its send time and the clocks are aligned."""
        age = client.clock.age_ms(float(msg.t)) if isinstance(msg.t, float | int) else None
        self.recorder.command(
            source="user",
            name=msg.name,
            args=msg.args,
            ok=ok,
            code=code,
            error=error,
            age_ms=age,
            seq=msg.seq,
        )

    def _record_safe_action(
        self, source: Source, action: str, failure: Exception | None, *, cause: str
    ) -> None:
        self.recorder.command(
            source=source,
            name=action,
            args={"cause": cause},
            ok=failure is None,
            code=None if failure is None else getattr(failure, "code", type(failure).__name__),
            error=None if failure is None else str(failure),
        )

    async def _send(self, client: _Client, message: Message) -> None:
        with contextlib.suppress(ConnectionError):
            await client.link.send(message)

    def _stop_client_tasks(self, client: _Client) -> None:
        for task in (client.telemetry, client.worker, client.offering):
            if task:
                task.cancel()

    async def _drop(self, client: _Client, code: int, reason: str) -> None:
        self._stop_client_tasks(client)
        # Close in the background: awaiting the closing handshake from inside the
        # client's own reader would deadlock once its unread frames fill the queue.
        self._spawn(client.link.close(code, reason))
        await self.disconnected(client.link)

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.ensure_future(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)


def _video_status_message(status: Any) -> VideoStatus:
    return VideoStatus(
        width=status.width, height=status.height, fps=status.fps, bitrate=status.bitrate
    )


class _WebSocketLink:
    """A ClientLink over a direct WebSocket."""

    _ids = itertools.count(1)
    path = "websocket"

    def __init__(self, ws: ServerConnection) -> None:
        self.ws = ws
        self.id = f"ws-{next(self._ids)}"

    async def send(self, message: Message) -> None:
        try:
            await self.ws.send(encode_message(message))
        except ConnectionClosed as exc:
            raise ConnectionError(str(exc)) from None

    async def close(self, code: int, reason: str) -> None:
        await self.ws.close(code, reason)


class ControlServer:
    """The agent's WebSocket endpoint for users (an async context manager).

    ``port=0`` picks a free port; :attr:`port` tells which after start.
    """

    def __init__(self, hub: ControlHub, *, host: str = "127.0.0.1", port: int = 0) -> None:
        self.hub = hub
        self.host = host
        self.port = port
        self._server: Server | None = None

    async def _handle(self, ws: ServerConnection) -> None:
        link = _WebSocketLink(ws)
        await self.hub.connected(link)
        try:
            async for raw in ws:
                await self.hub.received(link, raw)
        except ConnectionClosed:
            pass  # an oversized frame or a dead peer: the socket is closed either way
        finally:
            await self.hub.disconnected(link)

    async def start(self) -> None:
        self._server = await serve(
            self._handle,
            self.host,
            self.port,
            max_size=MAX_MESSAGE_BYTES,
            compression=None,  # latency over bandwidth: commands are tiny
            ping_interval=5,
            ping_timeout=5,
        )
        sock = next(iter(self._server.sockets))
        self.port = sock.getsockname()[1]

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()
