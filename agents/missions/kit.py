"""The flight kit every mission's runner is built on.

:class:`MissionRunner` flies one mission for one session with the vehicle's ordinary
commands, through :meth:`agents.control.ControlHub.mission_execute`: the same lock as
users' commands and fail-safes (never interleaved), the task's ceiling and geofence,
and only while the session is current and nobody took over. A runner subclass writes
only :meth:`MissionRunner.fly` from the steps here:

* :meth:`~MissionRunner.take_off_if_needed` (a vehicle on the surface is armed instead),
  :meth:`~MissionRunner.fly_to`, :meth:`~MissionRunner.descend` and
  :meth:`~MissionRunner.climb` (nothing for a vehicle on the surface),
  :meth:`~MissionRunner.hold_for`, :meth:`~MissionRunner.release_over` (a payload is
  released once ever per mission id), :meth:`~MissionRunner.return_home`;
* :meth:`~MissionRunner.until` waits for a state, each leg with a time limit from its
  distance and speed, and can ``sample`` a sensor on every turn (the search's thermal
  camera);
* :meth:`~MissionRunner.progress` and :meth:`~MissionRunner.report` tell the platform
  (``mission_progress`` on every phase change and waypoint, then the mission's events);
* :meth:`~MissionRunner.photograph` takes a geotagged picture with the agent's photo
  camera and :meth:`~MissionRunner.keep` keeps a file the mission made, both uploaded
  to the platform until it has them (agents.stills, agents.artifacts);
* :meth:`~MissionRunner.fly_natively` hands a mission of plain waypoints and actions
  (a :class:`~agents.missions.plan.FlightPlan`) to the vehicle's own mission engine when
  it has one (ArduPilot's AUTO): the autopilot flies it, and finishes it (home, or
  holding at its end) or returns home if the agent dies; the runner follows it and
  reports the same progress and events. A runner calls it first and flies its steps
  itself when it returns False; an upload the engine refused is reported
  (``native_mission_refused``), so that nobody believes the autopilot has the mission,
  and a mission the engine flies is too (``native_mission_started``, with ``within_s``,
  how long it may take at most), so that the platform waits for a vehicle gone silent
  that flies on by itself. An agent restarted mid-mission finds the engine flying the
  same plan (read back from the autopilot) and follows it, flying nothing again.

Whatever ends the mission is handled here once for all: a user command or a fail-safe
during the mission (``mission_failed``, "interrupted", the vehicle left to whoever
took over); an adapter error, a step that cannot finish (:class:`StepFailed`) or a bug
(``mission_failed``, and the vehicle holds where it is: ``stop``).
"""

from __future__ import annotations

import abc
import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from typing import Any, ClassVar, Final, Generic, Protocol, TypeAlias, TypeVar

from agents.geo import distance_m
from agents.missions.plan import FlightPlan, PlanStep
from agents.missions.spec import LatLon, MissionSpec
from agents.safety import Refusal
from agents.vehicles.base import Adapter, AdapterError, VehicleState
from agents.vehicles.plan import NativeMissions, PlanItem, Release, TakeOff

log = logging.getLogger(__name__)

Reporter: TypeAlias = Callable[[str, str | None, dict[str, Any]], None]

#: The agent's sensors entry of its photo camera (agents.stills.PHOTO_SECTION; named
#: here so that the kit loads no camera code).
PHOTO_SECTION: Final = "photo"
#: A waypoint counts as reached within this horizontal distance.
ARRIVE_M: Final = 3.0
#: Above this the vehicle counts as flying (below it a mission takes off first).
MIN_FLYING_M: Final = 1.0
#: Holding over a point (the person, the drop) means slower than this (m/s) there.
SETTLED_MPS: Final = 0.5
#: An altitude counts as reached within this much.
ALTITUDE_TOLERANCE_M: Final = 1.0
#: Per-leg time limit: this much plus LEG_TIME_FACTOR x (distance / speed).
LEG_MARGIN_S: Final = 30.0
LEG_TIME_FACTOR: Final = 3.0
#: Climb or descent rate assumed for the time limit of a vertical move (m/s).
VERTICAL_RATE_MPS: Final = 1.0
#: How often the position is checked when no sensor paces the loop.
POLL_S: Final = 0.1
#: An armed vehicle whose altitude is not known yet (an agent just started, its
#: telemetry a moment behind the autopilot's heartbeat) is waited for this long before
#: a take-off is judged needed: one sent to a vehicle flying is refused.
STATE_WAIT_S: Final = 5.0

_S = TypeVar("_S", bound=MissionSpec)


class MissionHub(Protocol):
    """What a runner needs from the agent's ControlHub (see its mission_execute)."""

    overrides: int
    override_reason: str
    autonomous: bool

    async def mission_execute(
        self, session_id: str, name: str, args: Mapping[str, Any], *, epoch: int
    ) -> None: ...

    async def mission_native_upload(
        self, session_id: str, items: Sequence[PlanItem], *, epoch: int
    ) -> None: ...

    async def mission_native_adopt(
        self, session_id: str, items: Sequence[PlanItem], *, epoch: int
    ) -> bool: ...

    async def mission_native_start(self, session_id: str, *, epoch: int) -> None: ...


class ArtifactSink(Protocol):
    """Where a runner keeps the files its mission makes until the platform has them
    (the agent's :class:`agents.artifacts.ArtifactStore`)."""

    def put(
        self, session_id: str, name: str, body: bytes, *, media_type: str, meta: Mapping[str, Any]
    ) -> bool: ...


class Interrupted(Exception):
    """Someone else acts on the vehicle (a user, a fail-safe, the autopilot itself): the
    mission ends without sending anything more."""


class StepFailed(Exception):
    """A step could not be completed (timeout, sensor failure): the mission ends and the
    vehicle holds. The message is the reason the platform hears."""


class MissionRunner(abc.ABC, Generic[_S]):
    """Flies one mission (its spec, ``mission``) for one session.

    ``start()`` runs it in a task (after ``previous``, a replaced runner's task, has
    finished cancelling); ``cancel()`` stops it without touching the vehicle (the
    caller decides what the vehicle does next). After it ends, ``result`` holds the
    terminal event reported (``(event, data)``, one of :attr:`RESULT_EVENTS` or
    ``mission_failed``), ``phase`` the last phase. ``released`` and
    ``release_attempted`` are shared with the agent's
    :class:`~agents.missions.control.MissionControl` so a payload is never released
    twice whatever happens to the runner. ``sensors`` are the agent's open sensors by
    configuration section (see :class:`agents.missions.registry.Sensor`); ``artifacts``
    keeps the files the mission makes (:meth:`keep`).
    """

    #: The events that end this mission well: a re-sent task for it hears them again.
    RESULT_EVENTS: ClassVar[frozenset[str]] = frozenset({"payload_released"})

    def __init__(
        self,
        mission: _S,
        *,
        session_id: str,
        hub: MissionHub,
        adapter: Adapter,
        report: Reporter,
        sensors: Mapping[str, Any] | None = None,
        artifacts: ArtifactSink | None = None,
        released: dict[str, dict[str, Any]] | None = None,
        release_attempted: set[str] | None = None,
        arrive_m: float = ARRIVE_M,
    ) -> None:
        self.mission = mission
        self.session_id = session_id
        self.hub = hub
        self.adapter = adapter
        self.sensors: Mapping[str, Any] = sensors or {}
        self.artifacts = artifacts
        self.arrive_m = arrive_m
        self.released = released if released is not None else {}
        self.release_attempted = release_attempted if release_attempted is not None else set()
        self._report_fn = report
        self.phase: str | None = None
        self.result: tuple[str, dict[str, Any]] | None = None
        #: What ``mission_progress`` reports as ``of`` (a search's waypoint count).
        self.progress_of: int | None = None
        self.task: asyncio.Task[None] | None = None
        self.cancelled = False
        self._epoch = 0
        self._mode: str | None = None

    @abc.abstractmethod
    async def fly(self) -> None:
        """The mission, from the steps of this kit. Raise StepFailed (the vehicle then
        holds) for anything that keeps it from finishing."""

    @property
    def done(self) -> bool:
        return self.task is not None and self.task.done()

    def start(self, previous: asyncio.Task[None] | None = None) -> None:
        self.task = asyncio.create_task(self._run(previous), name=f"mission {self.mission.id}")

    def cancel(self) -> None:
        """Stop flying the mission (no command is sent)."""
        self.cancelled = True
        if self.task is not None:
            self.task.cancel()

    async def wait(self) -> None:
        """Until the runner has finished or finished cancelling."""
        if self.task is not None:
            await asyncio.wait([self.task])

    # --- reporting -----------------------------------------------------------------------
    def report(self, event: str, **data: Any) -> None:
        """Tell the platform ``event`` about this mission (its id added as ``mission``)."""
        payload = {"mission": self.mission.id, **data}
        if event in self.RESULT_EVENTS or (event == "mission_failed" and self.result is None):
            self.result = (event, payload)
        self._report_fn(event, self.session_id, payload)

    def keep(self, name: str, body: bytes, *, media_type: str, meta: Mapping[str, Any]) -> bool:
        """Keep a file the mission made (``name``: a plain file name, unique in the
        session; ``meta``: what it is, a small JSON object) until the platform has it,
        which tells the session's kind. False when the agent keeps no files or refused
        this one (too big, the disk full): the mission goes on without it."""
        if self.artifacts is None:
            return False
        return self.artifacts.put(self.session_id, name, body, media_type=media_type, meta=meta)

    async def photograph(self, name: str) -> dict[str, Any]:
        """Take a picture now with the agent's photo camera (its configuration's
        ``photo`` section, agents.stills), tagged with where the vehicle is, and
        :meth:`keep` it as the JPEG ``name``. Returns the picture's ``meta`` (``lat``,
        ``lon``, ``alt``, ``heading_deg``, ``t``, its size and field of view), with
        ``kept`` False when the agent could not keep it. Raises StepFailed when the
        vehicle has no photo camera or the camera fails."""
        camera = self.sensors.get(PHOTO_SECTION)
        if camera is None:
            raise StepFailed("this vehicle has no photo camera (the agent's photo section)")
        st = self.adapter.state()
        pose = {"lat": st.lat, "lon": st.lon, "alt": st.alt, "heading_deg": st.heading_deg}
        try:
            photo = await camera.capture(pose)
        except OSError as exc:
            raise StepFailed(f"the photo camera failed: {exc}") from exc
        kept = self.keep(name, photo.jpeg, media_type="image/jpeg", meta=photo.meta)
        return {**photo.meta, "kept": kept}

    def where(self) -> dict[str, Any]:
        """The vehicle's position for an event: ``lat``, ``lon``, ``alt`` (None unknown)."""
        st = self.adapter.state()
        return {
            "lat": None if st.lat is None else round(st.lat, 7),
            "lon": None if st.lon is None else round(st.lon, 7),
            "alt": None if st.alt is None else round(st.alt, 1),
        }

    def progress(self, phase: str, waypoint: int | None = None) -> None:
        """A ``mission_progress`` event: on a phase change or a waypoint reached."""
        self.phase = phase
        self.report(
            "mission_progress", phase=phase, waypoint=waypoint, of=self.progress_of, **self.where()
        )

    # --- the run -------------------------------------------------------------------------
    async def _run(self, previous: asyncio.Task[None] | None) -> None:
        if previous is not None:
            await asyncio.wait([previous])  # never raises what ended it
        self._epoch = self.hub.overrides
        self.hub.autonomous = True
        try:
            await self.fly()
        except Interrupted as exc:
            log.warning("mission %s interrupted: %s", self.mission.id, exc)
            self.report("mission_failed", reason=f"interrupted: {exc}")
        except Refusal as exc:
            if exc.code == "no_task":
                return  # the session ended under us: the hub made the vehicle safe
            if exc.code == "overridden":
                self.report("mission_failed", reason=f"interrupted: {exc}")
                return
            self.report("mission_failed", reason=str(exc))
            await self._hold_after_failure()
        except (AdapterError, StepFailed) as exc:
            log.warning("mission %s failed: %s", self.mission.id, exc)
            self.report("mission_failed", reason=str(exc))
            await self._hold_after_failure()
        except Exception as exc:  # a bug must not end the agent; the vehicle holds
            log.exception("mission %s crashed", self.mission.id)
            self.report("mission_failed", reason=f"internal error: {exc!r}")
            await self._hold_after_failure()
        finally:
            self.hub.autonomous = False

    async def _hold_after_failure(self) -> None:
        """Stop where it is (hover); never raises."""
        try:
            await self.hub.mission_execute(self.session_id, "stop", {}, epoch=self._epoch)
        except (AdapterError, Refusal) as exc:
            log.warning("mission %s: could not hold: %s", self.mission.id, exc)

    async def command(self, name: str, args: Mapping[str, Any]) -> None:
        """Send one command of the vehicle's vocabulary (see :meth:`_within_declared`)."""
        self._check_interference()
        await self.hub.mission_execute(
            self.session_id, name, self._within_declared(name, args), epoch=self._epoch
        )
        # The mode our own command left the vehicle in; any other change is not ours.
        self._mode = self.adapter.state().mode

    def _within_declared(self, name: str, args: Mapping[str, Any]) -> dict[str, Any]:
        """``args`` with a speed above the vehicle's declared top speed lowered to it
        (the plan may ask for more than this airframe does), and the arguments the
        vehicle does not declare dropped (a boat's waypoint takes no altitude; one
        without a speed argument goes at its own cruise speed)."""
        spec = next((c.args for c in self.adapter.commands() if c.name == name), None)
        if spec is None:
            return dict(args)
        out = {key: value for key, value in args.items() if key in spec}
        declared = spec.get("speed_mps")
        if (
            "speed_mps" in out
            and declared is not None
            and isinstance(declared.get("max"), int | float)
        ):
            out["speed_mps"] = min(float(out["speed_mps"]), float(declared["max"]))
        return out

    def on_surface(self) -> bool:
        """A vehicle that cannot take off (a boat, a car): no climbs, no descents."""
        return not any(c.name == "take_off" for c in self.adapter.commands())

    def _check_interference(self) -> None:
        if self.cancelled:
            # Belt and braces: a cancellation lost in some await must not let a
            # replaced or ended mission fly on.
            raise asyncio.CancelledError
        if self.hub.overrides != self._epoch:
            raise Interrupted(self.hub.override_reason or "a user command or fail-safe")
        mode = self.adapter.state().mode
        if self._mode is not None and mode is not None and mode != self._mode:
            raise Interrupted(f"the vehicle switched to {mode} by itself")

    # --- the steps -----------------------------------------------------------------------
    async def take_off_if_needed(self, altitude: float) -> None:
        """Take off to ``altitude`` unless flying already (``takeoff`` progress); a
        vehicle on the surface is armed instead (:meth:`arm_if_needed`)."""
        if self.on_surface():
            await self.arm_if_needed()
            return
        st = self.adapter.state()
        waited = time.monotonic() + STATE_WAIT_S
        while st.armed and st.alt is None and time.monotonic() < waited:
            await asyncio.sleep(POLL_S)
            st = self.adapter.state()
        in_air = self.adapter.telemetry().get("in_air")
        if in_air is None:  # an adapter without the topic: judge by the altitude
            in_air = bool(st.armed) and st.alt is not None and st.alt >= MIN_FLYING_M
        if in_air and st.alt is not None and st.alt >= MIN_FLYING_M:
            return  # already flying
        self.progress("takeoff")
        target = altitude
        if in_air:
            # A take-off is under way (a replaced mission started it): let it clear
            # the ground; the first waypoint sets this mission's altitude.
            target = MIN_FLYING_M + ALTITUDE_TOLERANCE_M
        else:
            await self.command("take_off", {"altitude_m": altitude})
        await self.until(
            lambda s: s.alt is not None and s.alt >= target - ALTITUDE_TOLERANCE_M,
            timeout_s=LEG_MARGIN_S + target / VERTICAL_RATE_MPS,
            what=f"the climb to {target:g} m",
        )

    async def arm_if_needed(self) -> None:
        """A vehicle on the surface has nothing to take off, but its autopilot drives
        only armed (a boat's ArduRover refuses a waypoint before): arm it. Nothing when
        it is armed already, or has no ``arm`` command (it needs none)."""
        if self.adapter.state().armed or not any(c.name == "arm" for c in self.adapter.commands()):
            return
        await self.command("arm", {})

    async def fly_to(
        self,
        point: LatLon,
        altitude: float,
        *,
        speed: float,
        settle: bool = False,
        sample: Callable[[], Awaitable[None]] | None = None,
    ) -> None:
        """go_to_waypoint and wait to be within ``arrive_m`` of it (horizontally);
        ``settle``: and slowed down to a hover there (a pass through the radius at
        cruise speed is not a hold); ``sample``: see :meth:`until`."""
        st = self.adapter.state()
        here = st.position
        distance = distance_m(here, point) if here is not None else 1000.0
        climb = 0.0 if self.on_surface() else abs(altitude - (st.alt or 0.0))

        def arrived(s: VehicleState) -> bool:
            if s.position is None or distance_m(s.position, point) > self.arrive_m:
                return False
            return not settle or s.speed_mps is None or s.speed_mps <= SETTLED_MPS

        await self.command(
            "go_to_waypoint",
            {"lat": point[0], "lon": point[1], "alt_m": altitude, "speed_mps": speed},
        )
        await self.until(
            arrived,
            timeout_s=LEG_MARGIN_S
            + LEG_TIME_FACTOR * (distance / speed + climb / VERTICAL_RATE_MPS),
            what=f"the flight to {point[0]:.6f}, {point[1]:.6f}",
            sample=sample,
        )

    async def until(
        self,
        done: Callable[[VehicleState], bool],
        *,
        timeout_s: float,
        what: str,
        sample: Callable[[], Awaitable[None]] | None = None,
    ) -> None:
        """Wait for ``done(state)``, watching for interference; raises StepFailed after
        ``timeout_s``. With ``sample`` the loop awaits it on every turn instead of
        polling every :data:`POLL_S` (a sensor paces the loop and may raise to end the
        leg: the search's thermal camera, which raises on a detection)."""
        deadline = time.monotonic() + timeout_s
        while True:
            self._check_interference()
            if done(self.adapter.state()):
                return
            if time.monotonic() > deadline:
                raise StepFailed(f"{what} did not finish within {timeout_s:.0f} s")
            if sample is not None:
                await sample()
            else:
                await asyncio.sleep(POLL_S)

    async def descend(self, point: LatLon, high: float, low: float, speed: float) -> None:
        """Down to ``low`` over ``point`` (nothing for a vehicle on the surface)."""
        if self.on_surface():
            return
        await self.fly_to(point, low, speed=speed, settle=True)
        await self.until(
            lambda s: s.alt is not None and s.alt <= low + ALTITUDE_TOLERANCE_M,
            timeout_s=LEG_MARGIN_S + (high - low) / VERTICAL_RATE_MPS,
            what=f"the descent to {low:g} m",
        )

    async def climb(self, point: LatLon, low: float, high: float, speed: float) -> None:
        """Back up to ``high`` over ``point`` (nothing for a vehicle on the surface)."""
        if self.on_surface():
            return
        await self.fly_to(point, high, speed=speed)
        await self.until(
            lambda s: s.alt is not None and s.alt >= high - ALTITUDE_TOLERANCE_M,
            timeout_s=LEG_MARGIN_S + (high - low) / VERTICAL_RATE_MPS,
            what=f"the climb back to {high:g} m",
        )

    async def release_over(self, point: LatLon, high: float, low: float, speed: float) -> None:
        """Descend over ``point``, release the payload once ever for this mission's id
        (``payload_released``), climb back."""
        mission_id = self.mission.id
        await self.descend(point, high, low, speed)
        if mission_id in self.release_attempted:
            raise StepFailed("this mission's payload release was already attempted")
        # Recorded before sending: whatever the answer, it is never sent twice.
        self.release_attempted.add(mission_id)
        await self.command("release_payload", {})
        where = self.where()
        self.released[mission_id] = {
            "mission": mission_id,
            "lat": where["lat"],
            "lon": where["lon"],
        }
        self.report("payload_released", lat=where["lat"], lon=where["lon"])
        await self.climb(point, low, high, speed)

    async def hold_for(self, seconds: float) -> None:
        """Stay put for ``seconds``, still watching for interference."""
        until = time.monotonic() + seconds
        await self.until(
            lambda _s: time.monotonic() >= until,
            timeout_s=seconds + LEG_MARGIN_S,
            what=f"a wait of {seconds:g} s",
        )

    async def return_home(self) -> None:
        """Fly home with the vehicle's own ``return_to_home`` (``returning`` progress;
        a copter lands there). The session stays open: its users watch the way back."""
        self.progress("returning")
        await self.command("return_to_home", {})

    # --- the vehicle's own mission engine ------------------------------------------------
    async def fly_natively(self, plan: FlightPlan) -> bool:
        """Fly ``plan`` with the vehicle's own mission engine, if it has one: upload it
        (on the ground or in the air), take off if needed (in GUIDED, as a ground
        station does: ArduCopter arms in no AUTO), start it, and follow it until its
        last step, the return home or the hold, has begun (as :meth:`return_home`
        ends a mission flown step by step, or its last leg and a ``hold`` progress),
        reporting each step's ``phase`` and ``event``. After a hold the vehicle stays
        there in the engine's own mission (AUTO) until someone sends it elsewhere.

        An engine that flies ``plan`` already (this agent restarted mid-mission: see
        :meth:`agents.control.ControlHub.mission_native_adopt`) is followed from where
        it is, nothing uploaded or flown again; the steps it passed meanwhile are
        reported then.

        Returns False, having flown nothing, when the vehicle has no engine or refuses
        the upload: the runner then flies its steps itself. A refusal is reported to the
        platform (``native_mission_refused``, with the autopilot's reason), since it
        changes what the vehicle does if the agent dies: its fail-safe then acts on a
        vehicle the agent flies (GUIDED), with no mission of its own to finish.
        Raises as the steps do: Interrupted when someone else acts on the vehicle
        (the autopilot's own fence or fail-safe included), StepFailed when the plan
        takes too long or its payload release was attempted already."""
        engine = self.adapter.native_missions()
        if engine is None:
            return False
        self._check_interference()
        if await self.hub.mission_native_adopt(self.session_id, plan.items, epoch=self._epoch):
            # This agent restarted while the autopilot flew the plan: followed from
            # where it is; what it did meanwhile (a release too) is reported as done.
            log.info("mission %s: the autopilot flies it already: followed", self.mission.id)
            if plan.releases:
                self.release_attempted.add(self.mission.id)
            await self._follow(plan, engine, self._plan_deadline(plan), adopted=True)
            return True
        if plan.releases and self.mission.id in self.release_attempted:
            raise StepFailed("this mission's payload release was already attempted")
        self._check_interference()
        try:
            await self.hub.mission_native_upload(self.session_id, plan.items, epoch=self._epoch)
        except AdapterError as exc:
            log.warning("mission %s: flown step by step: %s", self.mission.id, exc)
            self.report("native_mission_refused", reason=str(exc))
            return False
        first = next((s.item for s in plan.steps if isinstance(s.item, TakeOff)), None)
        if first is not None:
            await self.take_off_if_needed(first.altitude_m)
        deadline = self._plan_deadline(plan)
        if plan.releases:
            # Recorded before the autopilot may release it: never sent twice.
            self.release_attempted.add(self.mission.id)
        self._check_interference()
        await self.hub.mission_native_start(self.session_id, epoch=self._epoch)
        await self._follow(plan, engine, deadline)
        return True

    def _plan_deadline(self, plan: FlightPlan) -> float:
        """When (monotonic) the engine must be done with ``plan``, flown from here."""
        st = self.adapter.state()
        return time.monotonic() + plan.time_limit_s(st.position, st.alt or 0.0)

    async def _follow(
        self, plan: FlightPlan, engine: NativeMissions, deadline: float, *, adopted: bool = False
    ) -> None:
        """Tell the platform the engine flies the plan (``native_mission_started``), then
        report the plan's steps as the engine starts and passes them; return once its
        last step (the return home, or the hold the engine never moves past) has
        started. ``adopted``: the engine was found flying the plan; of the phases it
        went through before, only the one it is in is reported (the events, facts the
        platform may not have heard, all are)."""
        self._mode = self.adapter.state().mode
        # The platform then knows the vehicle flies on if its agent goes silent, and
        # for how long at most: it sends no other vehicle there meanwhile.
        within = round(deadline - time.monotonic())
        self.report("native_mission_started", within_s=within, adopted=adopted)
        steps = plan.steps
        started = finished = -1
        last = len(steps) - 1
        while True:
            self._check_interference()
            where = engine.mission_progress()
            current = len(steps) if where.finished else where.current
            if current is not None:
                # Steps the engine moved past (a "do" step is never current) in order.
                passed = range(started + 1, min(current, last) + 1)
                phases = [p for p in (steps[i].phase for i in passed) if p is not None]
                started = max(started, min(current, last))
                for phase in phases[-1:] if adopted else phases:
                    self.progress(phase)
                adopted = False
                for index in range(finished + 1, min(current, len(steps))):
                    finished = index
                    self._step_done(steps[index])
                if started >= last:
                    return
            if time.monotonic() > deadline:
                raise StepFailed(f"the autopilot's mission did not finish at step {current}")
            await asyncio.sleep(POLL_S)

    def _step_done(self, step: PlanStep) -> None:
        """A step of a plan the engine finished: its event, and a release's record."""
        if step.event is None:
            return
        where = self.where()
        if isinstance(step.item, Release):
            mission_id = self.mission.id
            self.released[mission_id] = {
                "mission": mission_id,
                "lat": where["lat"],
                "lon": where["lon"],
            }
            self.report(step.event, lat=where["lat"], lon=where["lon"])
            return
        self.report(step.event, **where)
