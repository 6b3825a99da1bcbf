"""The agent program: one vehicle's adapter, control server, video and uplink."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import signal
import time
from collections.abc import Callable, Coroutine, Mapping
from typing import Any
from urllib.parse import urlsplit

import msgspec

from agents.artifacts import ArtifactStore
from agents.config import AgentConfig, is_loopback_host
from agents.control import ControlHub, ControlServer
from agents.missions.control import MissionControl
from agents.missions.registry import sensors as mission_sensors
from agents.protocol import (
    KeySet,
    ProtocolError,
    ReplayGuard,
    VehicleTask,
    claimed_session,
)
from agents.protocol.messages import (
    Ack,
    CommandSpec,
    EndTask,
    Error,
    Event,
    Heartbeat,
    Message,
    Position,
    Profile,
    RelayClose,
    RelayToAgent,
    RelayToPlatform,
    Revoke,
    Task,
    TaskAccepted,
    TaskRefused,
    message_type,
)
from agents.recording import FlightRecorder
from agents.safety import Refusal
from agents.uplink import Uplink
from agents.vehicles.base import Adapter
from agents.vehicles.registry import adapter_create

log = logging.getLogger(__name__)

#: Relayed browsers one agent serves at once (each is a viewer or the controller).
MAX_RELAYED = 64
#: Faster than this (m/s) with no task, a vehicle is still on its way home by itself.
UNDER_WAY_MPS = 0.5


class Agent:
    """Runs one vehicle until cancelled; see ``python -m agents run --help``.

    After :meth:`run` has started, :attr:`ready` is set once the control server listens
    (its URL in :attr:`control_url`); :attr:`uplink` tells whether the platform is
    connected.
    """

    def __init__(self, config: AgentConfig, *, adapter: Adapter | None = None) -> None:
        self.config = config
        #: The platform keys tasks and grants are verified with; replaced by the key set
        #: of a trusted ``welcome`` (see :meth:`on_welcome`).
        self.keys: KeySet = config.platform_keys()
        self.adapter = adapter or adapter_create(config.adapter, config.adapter_options)
        self.tasks_seen = ReplayGuard()
        self.ready = asyncio.Event()
        self.control_url = ""
        self.hub: ControlHub | None = None
        self.uplink: Uplink | None = None
        self.video: Any | None = None
        #: The open sensors the missions need, by configuration section (the search's
        #: ``thermal`` camera: a ThermalFeed); see agents.missions.registry.Sensor.
        self.sensors: dict[str, Any] = {}
        self.missions: MissionControl | None = None
        self.relay_links: dict[str, _RelayLink] = {}
        #: The publisher of the camera to the platform's SFU for the current task's
        #: spectators (agents.sfu), with the session it publishes for.
        self.sfu: Any | None = None
        self._sfu_job: asyncio.Task[None] | None = None
        self._sfu_session: str | None = None
        self._checks: set[asyncio.Task[None]] = set()
        self.adapter.on_event = self._adapter_event
        #: The flight record of each session (agents.recording).
        self.recorder = FlightRecorder(
            directory=config.records.path_for(config.vehicle_id),
            state=self.adapter.state,
            telemetry=self.adapter.telemetry,
            max_bytes=config.records.max_bytes,
        )
        self.adapter.on_raw = self.recorder.raw
        #: The files missions make (their photos), kept until the platform has them.
        self.artifacts = ArtifactStore(
            directory=config.records.artifacts_path_for(config.vehicle_id),
            max_bytes=config.records.max_bytes,
        )

    def _adapter_event(self, name: str, data: dict[str, Any]) -> None:
        """Something the vehicle itself reported (autopilot link, low battery...):
        the platform hears it, attached to the current session if there is one."""
        task = self.hub.task if self.hub is not None else None
        self.report(name, task.session_id if task else None, data)

    async def run(self) -> None:
        """Start everything, serve until cancelled, then leave the vehicle safe."""
        async with contextlib.AsyncExitStack() as stack:
            # Entered first, left last: it writes what the hub's shutdown recorded.
            await stack.enter_async_context(self.recorder)
            await stack.enter_async_context(self.artifacts)
            await stack.enter_async_context(self.adapter)
            for section, options in self.config.sensors.items():
                sensor = mission_sensors()[section].create(options, self._camera_pose)
                self.sensors[section] = await stack.enter_async_context(sensor)
            if self.config.photo is not None:
                # Imported here: numpy and Pillow only for an agent with a photo camera.
                from agents.stills import PHOTO_SECTION, still_camera_create

                camera = still_camera_create(self.config.photo)
                self.sensors[PHOTO_SECTION] = await stack.enter_async_context(camera)
            if self.config.video is not None:
                self.video = await stack.enter_async_context(self._video_service())
            hub = ControlHub(
                vehicle_id=self.config.vehicle_id,
                vehicle_name=self.config.name,
                public_key=self.keys,
                adapter=self.adapter,
                report=self.report,
                video=self.video,
                on_task_end=self._task_ended,
                webrtc=self.config.webrtc,
                max_grant_lifetime_s=self.config.control.max_grant_lifetime_s,
                recorder=self.recorder,
            )
            self.hub = await stack.enter_async_context(hub)
            self.missions = MissionControl(
                hub=hub,
                adapter=self.adapter,
                report=self.report,
                sensors=self.sensors,
                artifacts=self.artifacts,
            )
            # Closed before the hub and the adapter (exit order is reversed).
            stack.push_async_callback(self.missions.close)
            server = await stack.enter_async_context(
                ControlServer(hub, host=self.config.control.host, port=self.config.control.port)
            )
            self.control_url = (
                self.config.control.public_url or f"ws://{self.config.control.host}:{server.port}/"
            )
            self.uplink = Uplink(
                url=self.config.uplink_url,
                vehicle_id=self.config.vehicle_id,
                credential=self.config.credential,
                on_message=self.on_platform_message,
                profile=self.profile,
                heartbeat=self.heartbeat,
                reconnect_min_s=self.config.reconnect_min_s,
                reconnect_max_s=self.config.reconnect_max_s,
                on_welcome=self.on_welcome,
                ping_interval_s=self.config.uplink_ping_interval_s,
                ping_timeout_s=self.config.uplink_ping_timeout_s,
            )
            self.recorder.uplink = self.uplink
            self.artifacts.uplink = self.uplink
            stack.callback(self._sfu_stop)
            self.ready.set()
            log.info(
                "%s: control on %s", self.config.name or self.config.vehicle_id, self.control_url
            )
            await self.uplink.run()

    def _video_service(self) -> Any:
        # Imported here: aiortc and av are only loaded by agents with a camera.
        from agents.video.service import video_service_create

        # A sensor that shows as video (the thermal camera) is a source by its section.
        sources = {
            section: functools.partial(video, self.sensors[section])
            for section, sensor in mission_sensors().items()
            if section in self.sensors and (video := sensor.video) is not None
        }
        return video_service_create(
            self.config.video or {}, pose=self._camera_pose, sources=sources
        )

    def _camera_pose(self) -> dict[str, Any]:
        """Where the camera is and looks, for the synthetic camera."""
        state = self.adapter.state()
        telemetry = self.adapter.telemetry()
        return {
            "lat": state.lat,
            "lon": state.lon,
            "alt": state.alt,
            "heading_deg": state.heading_deg,
            "pan_deg": telemetry.get("camera_pan"),
            "tilt_deg": telemetry.get("camera_tilt"),
        }

    # --- what the platform hears ---------------------------------------------------------
    def profile(self) -> Profile:
        """The ``profile`` sent on every registration: what the vehicle is and offers,
        and what it is doing now (its task's session, whether a user controls it, its
        status), from which the platform converges it to what it should be doing."""
        state = self.adapter.state()
        hub = self.hub
        task = hub.task if hub is not None else None
        return Profile(
            vehicle_type=str(self.config.adapter_options.get("vehicle_type", self.adapter.name)),
            adapter=self.adapter.name,
            attributes=dict(self.config.adapter_options.get("attributes", {})),
            commands=[
                msgspec.convert(c.to_profile(), CommandSpec) for c in self.adapter.commands()
            ],
            telemetry=self.adapter.telemetry_topics(),
            control_url=self.control_url,
            video=self.video is not None,
            sfu=self.video is not None,
            safe_actions=dict(self.adapter.safe_action_words),
            position=self._position(),
            battery=state.battery,
            session_id=task.session_id if task is not None else None,
            controller=hub is not None and hub.controller is not None,
            status=self._status(),
        )

    def heartbeat(self) -> Heartbeat:
        """The next heartbeat; the uplink numbers it (``seq``)."""
        return Heartbeat(
            seq=0,
            position=self._position(),
            battery=self.adapter.state().battery,
            status=self._status(),
        )

    def _status(self) -> str:
        hub = self.hub
        if hub is not None and hub.task is not None:
            return "in_service"
        if self._airborne() or self._under_way():
            return "returning"  # still flying or sailing home, or landing, on its own
        return "idle"

    def _airborne(self) -> bool:
        """True while the vehicle is still in the air (telemetry ``in_air`` or an
        altitude above half a metre): it is not free for another session yet."""
        telemetry = self.adapter.telemetry()
        if telemetry.get("in_air"):
            return True
        altitude = telemetry.get("altitude")
        return isinstance(altitude, int | float) and altitude > 0.5

    def _under_way(self) -> bool:
        """True while a vehicle on the surface still moves by itself after its task
        (a boat sailing home): it is not free for another session until it stops."""
        speed = self.adapter.state().speed_mps
        return speed is not None and speed > UNDER_WAY_MPS

    def _position(self) -> Position | None:
        state = self.adapter.state()
        if state.lat is None or state.lon is None:
            return None
        return Position(lat=state.lat, lon=state.lon, alt=state.alt)

    def report(self, event: str, session_id: str | None, data: dict[str, Any]) -> None:
        """Tell the platform about a session event (queued while it is unreachable),
        with the time it happened now, by the vehicle's clock; the session's flight
        record keeps it too."""
        self.recorder.event(event, session_id, data)
        if self.uplink is not None:
            self.uplink.send(
                Event(session_id=session_id, event=event, data=data, at=round(time.time(), 3))
            )

    # --- what the platform says ----------------------------------------------------------
    def on_welcome(self, msg: Any) -> None:
        """Adopt the key set the platform's ``welcome`` carries (``platform_jwks``), so a
        key rotation reaches this agent without a new config.

        Only over an uplink whose server is authenticated (``wss://``, or ``ws://`` on
        loopback) and unless the config pins its keys; an unusable JWKS is logged and the
        keys in use are kept.
        """
        # A parsed message may be a dict or a message struct (absent field: UNSET).
        jwks = (
            msg.get("platform_jwks")
            if isinstance(msg, Mapping)
            else getattr(msg, "platform_jwks", None)
        )
        if not isinstance(jwks, Mapping) or not self.config.platform_jwks_from_welcome:
            return
        if not _server_authenticated(self.config.uplink_url):
            log.warning("ignored the welcome's platform keys: the uplink is not wss://")
            return
        try:
            keys = KeySet.from_jwks(jwks)
        except ProtocolError as exc:
            log.warning("ignored the welcome's platform keys: %s", exc)
            return
        if keys != self.keys:
            log.info("platform keys are now %s", keys.kids)
            self.keys = keys
            if self.hub is not None:
                self.hub.public_key = keys

    async def on_platform_message(self, msg: Message) -> None:
        hub = self.hub
        assert hub is not None and self.uplink is not None
        match msg:
            case Task():
                self._task(msg.token)
            case Revoke():
                await hub.task_end(msg.session_id, reason=msg.reason, action=msg.action)
            case EndTask():
                await hub.task_end(msg.session_id, reason=msg.reason, action=None)
            case RelayToAgent():
                await self._relayed(msg)
            case RelayClose():
                link = self.relay_links.pop(msg.conn, None)
                if link is not None:
                    await hub.disconnected(link)
            case Ack():
                if not self.recorder.acked(msg) and not self.artifacts.acked(msg):
                    log.info("ignored an ack of %s", msg.id)
            case Error():
                log.warning("platform error %s: %s", msg.code, msg.message)
            case _:
                log.info("ignored platform message %s", message_type(msg))

    async def _relayed(self, msg: RelayToAgent) -> None:
        """A control message from a browser relayed by the platform: same hub, same
        checks as a direct socket, answers sent back over the uplink."""
        assert self.hub is not None and self.uplink is not None
        conn = msg.conn
        if not conn:
            return
        link = self.relay_links.get(conn)
        if link is None:
            if len(self.relay_links) >= MAX_RELAYED:
                return
            link = _RelayLink(self, msg.session_id, conn)
            self.relay_links[conn] = link
            await self.hub.connected(link)
        if msg.ice_servers:
            # The platform's servers (fresh TURN credentials) for the offer it carries.
            link.ice_servers = [server.as_config() for server in msg.ice_servers]
        # The payload was parsed as a control_to_agent message with the uplink frame that
        # carried it; the hub's rate limit applies as on a direct socket.
        await self.hub.received(link, msg.payload)

    def _task(self, token: str) -> None:
        assert self.hub is not None and self.uplink is not None
        try:
            task = VehicleTask.verify(
                token,
                self.keys,
                vehicle_id=self.config.vehicle_id,
                replay_guard=self.tasks_seen,
            )
            self.hub.task_accept(task)
        except (ProtocolError, Refusal) as exc:
            log.warning("refused a task: %s", exc)
            self.uplink.send(
                TaskRefused(
                    session_id=claimed_session(token),
                    code=getattr(exc, "code", "refused"),
                    reason=str(exc),
                )
            )
            return
        self.uplink.send(TaskAccepted(session_id=task.session_id))
        self._sfu_start(task)
        if self.missions is not None:
            # After task_accepted: the platform hears the task before its mission events.
            self.missions.task_accepted(task)
        self._spawn_check(self._check_failsafe(task))

    def _task_ended(self, task: VehicleTask) -> None:
        if self._sfu_session == task.session_id:
            self._sfu_stop()
        if self.missions is not None:
            self.missions.task_ended(task)
        self._spawn_check(self._fence_clear(task))

    def _sfu_start(self, task: VehicleTask) -> None:
        """Publish the camera to the SFU room the task names, for its spectators (the
        same room again for a task sent again: the publisher goes on)."""
        sfu = task.sfu
        if sfu is None or self.video is None:
            self._sfu_stop()
            return
        current = self.sfu
        if (
            current is not None
            and self._sfu_session == task.session_id
            and (current.url, current.room, current.feed) == (sfu.url, sfu.room, sfu.feed)
        ):
            # The same room: publishing goes on, with the fresher token from now on
            # (Janus checks it on every request; an old one runs out).
            current.token = sfu.token
            return
        self._sfu_stop()
        # Imported here: aiortc is only loaded by agents with a camera.
        from agents.sfu import SfuPublisher

        self.sfu = SfuPublisher.for_room(
            self.video,
            sfu,
            display=self.config.name or self.config.vehicle_id,
            ice_servers=self.config.webrtc.get("ice_servers", ()),
        )
        self._sfu_session = task.session_id
        self._sfu_job = asyncio.create_task(self.sfu.run(), name="sfu publisher")

    def _sfu_stop(self) -> None:
        """Stop publishing (the task ended, or another room is named)."""
        if self._sfu_job is not None:
            self._sfu_job.cancel()
        self.sfu = self._sfu_job = self._sfu_session = None

    def _spawn_check(self, coro: Coroutine[Any, Any, None]) -> None:
        job = asyncio.create_task(coro)
        self._checks.add(job)
        job.add_done_callback(self._checks.discard)

    async def _check_failsafe(self, task: VehicleTask) -> None:
        """Does the vehicle's own fail-safe (an autopilot's) agree with the task? Report
        if not (see :meth:`Adapter.check_failsafe_params`). Then the task's limits go to
        the vehicle's own fence, the second line (:meth:`Adapter.fence_set`), reported as
        ``autopilot_fence_failed`` when that fails."""
        limits = task.limits
        try:
            problems = await self.adapter.check_failsafe_params(
                limits.failsafe_action, max_altitude_m=limits.max_altitude_m
            )
        except Exception as exc:  # a parameter read failing is itself worth reporting
            problems = [f"could not read the autopilot's fail-safe parameters: {exc}"]
        if problems:
            self.report("failsafe_mismatch", task.session_id, {"problems": list(problems)})
        fence = await self.adapter.fence_set(
            limits.failsafe_action,
            max_altitude_m=limits.max_altitude_m,
            geofence_center=limits.geofence_center,
            geofence_radius_m=limits.geofence_radius_m,
        )
        if fence:
            self.report("autopilot_fence_failed", task.session_id, {"problems": fence})

    async def _fence_clear(self, task: VehicleTask) -> None:
        """The task ended: the vehicle's own fence goes back to what it was."""
        problems = await self.adapter.fence_clear()
        if problems:
            self.report("autopilot_fence_failed", task.session_id, {"problems": problems})


class _RelayLink:
    """A ClientLink for a browser the platform relays (see services.consumers)."""

    path = "relay"

    def __init__(self, agent: Agent, session_id: str, conn: str) -> None:
        self.agent = agent
        self.session_id = session_id
        self.conn = conn
        self.id = f"relay-{conn}"
        #: STUN/TURN servers the platform sent with this user's last WebRTC offer.
        self.ice_servers: list[dict[str, Any]] = []

    async def send(self, message: Message) -> None:
        if self.agent.relay_links.get(self.conn) is not self or self.agent.uplink is None:
            raise ConnectionError("relayed client is gone")
        if not self.agent.uplink.connected.is_set():
            # Relayed control needs the platform; without it this client is cut off.
            raise ConnectionError("platform unreachable")
        payload: Any = message  # a control_to_client message: the hub sends no other
        self.agent.uplink.send(
            RelayToPlatform(session_id=self.session_id, conn=self.conn, payload=payload)
        )

    async def close(self, code: int, reason: str) -> None:
        if self.agent.relay_links.pop(self.conn, None) is None or self.agent.uplink is None:
            return
        self.agent.uplink.send(
            RelayClose(session_id=self.session_id, conn=self.conn, code=code, reason=reason[:120])
        )


def _server_authenticated(url: str) -> bool:
    """Is the platform at ``url`` authenticated: TLS (``wss``), or on this machine?"""
    parts = urlsplit(url)
    if parts.scheme == "wss":
        return True
    return is_loopback_host(parts.hostname or "")


def run_until_stopped(main: Callable[[], Coroutine[Any, Any, None]]) -> None:
    """Run ``main()`` until it returns or the process is told to stop: SIGINT (Ctrl-C)
    and SIGTERM (what systemd and container runtimes send) alike cancel it, so that
    every agent's exit stack runs: the vehicle performs its shutdown action (the task's
    fail-safe action while a task is current, else the adapter's own). A second signal
    during that is ignored: the shutdown finishes, bounded by the service manager's
    stop timeout."""

    async def guarded() -> None:
        task = asyncio.current_task()
        assert task is not None
        loop = asyncio.get_running_loop()
        stopping = False

        def stop(signum: signal.Signals) -> None:
            nonlocal stopping
            if stopping:
                log.warning("%s again: the shutdown is under way", signum.name)
                return
            stopping = True
            log.warning("%s: shutting down", signum.name)
            task.cancel()

        for signum in (signal.SIGINT, signal.SIGTERM):
            # Not every platform has loop signal handlers (Windows): Ctrl-C then stays
            # asyncio.run's own, which cancels the task too.
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(signum, stop, signum)
        await main()

    with contextlib.suppress(KeyboardInterrupt, asyncio.CancelledError):
        asyncio.run(guarded())


def agents_run_forever(configs: list[AgentConfig]) -> None:
    """Run several agents in one process (simulated fleets) until stopped (SIGINT,
    SIGTERM: see :func:`run_until_stopped`)."""

    async def main() -> None:
        await asyncio.gather(*(Agent(c).run() for c in configs))

    run_until_stopped(main)
