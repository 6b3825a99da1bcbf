"""Autonomous missions flown from the signed vehicle task (``VehicleTask.mission``).

The platform plans a mission and signs it into the task; the agent flies it with the
vehicle's ordinary commands and reports what happens as session events. Two kinds
(the full contract, events and behaviour are in docs/rescue-agent.md):

``search``
    take off if needed, fly the lawnmower ``waypoints`` from ``start_index`` at
    ``altitude_m`` while the thermal feed looks for persons; the first blob at
    ``min_confidence`` or more is reported once (``person_detected``) and the drone
    flies over it and holds. No detection: ``search_complete``, hold at the last
    waypoint.
``delivery``
    take off if needed, fly to ``target`` at ``altitude_m``, descend to
    ``drop_altitude_m``, release the payload once (``payload_released``), climb back
    and hold.
``return``
    fly home with the vehicle's own ``return_to_home`` (a copter lands there), the
    session still open: its users watch the way back (a rescue's last phase).
``parcel``
    take off if needed, fly to ``pickup``, descend to ``load_altitude_m`` and wait
    ``load_s`` for the parcel to be put on board (``parcel_loaded``), fly it to
    ``dropoff``, descend to ``drop_altitude_m``, release it once
    (``payload_released``) and return home. A vehicle on the surface (a boat: no
    ``take_off``, no altitude) sails it, armed first instead of taking off, without
    the climbs and descents.

Every command goes through :meth:`agents.control.ControlHub.mission_execute`: the same
lock as users' commands and fail-safes (never interleaved), the task's ceiling and
geofence, and only while the session is current and nobody took over. A user command
or a fail-safe during the mission ends it (``mission_failed``, the vehicle is left to
whoever took over); an adapter error ends it too and the vehicle holds (``stop``).

:class:`MissionControl` is what the agent holds: at most one runner at a time,
idempotent per mission id (a re-sent task never restarts or repeats anything; a
released payload is never released again).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Final, Protocol, TypeAlias

from agents.geo import distance_m
from agents.protocol import VehicleTask
from agents.safety import Refusal
from agents.thermal import Blob, ThermalError, ThermalFeed, ThermalFrame, geolocate
from agents.vehicles.base import Adapter, AdapterError, VehicleState

log = logging.getLogger(__name__)

LatLon: TypeAlias = tuple[float, float]
Reporter: TypeAlias = Callable[[str, str | None, dict[str, Any]], None]

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
#: The thermal feed must deliver a frame within this long during a search.
FRAME_TIMEOUT_S: Final = 5.0
#: How often the position is checked when no thermal frame paces the loop.
POLL_S: Final = 0.1
MAX_WAYPOINTS: Final = 2000
MAX_ALTITUDE_M: Final = 500.0
MAX_SPEED_MPS: Final = 50.0
#: Finished missions whose result a re-sent task hears again.
REMEMBERED: Final = 256

#: Terminal events: what a re-sent task for a finished mission hears again.
RESULT_EVENTS: Final = ("person_detected", "payload_released", "search_complete")


class MissionError(ValueError):
    """The task's mission is malformed; the message names the field."""


@dataclass(frozen=True)
class SearchMission:
    """Fly ``waypoints[start_index:]`` at ``altitude_m`` looking for a person."""

    id: str
    altitude_m: float
    speed_mps: float
    waypoints: tuple[LatLon, ...]
    start_index: int = 0
    min_confidence: float = 0.6
    kind: str = "search"


@dataclass(frozen=True)
class DeliveryMission:
    """Drop the payload over ``target`` from ``drop_altitude_m``."""

    id: str
    target: LatLon
    altitude_m: float
    drop_altitude_m: float
    speed_mps: float
    kind: str = "delivery"


@dataclass(frozen=True)
class ParcelMission:
    """Collect a parcel at ``pickup``, release it at ``dropoff``, go home."""

    id: str
    pickup: LatLon
    dropoff: LatLon
    altitude_m: float
    load_altitude_m: float
    load_s: float
    drop_altitude_m: float
    speed_mps: float
    kind: str = "parcel"


@dataclass(frozen=True)
class ReturnMission:
    """Go home (``return_to_home``) while the session stays open."""

    id: str
    kind: str = "return"


Mission: TypeAlias = SearchMission | DeliveryMission | ParcelMission | ReturnMission

_FIELDS: Final = {
    "search": {
        "kind",
        "id",
        "altitude_m",
        "speed_mps",
        "waypoints",
        "start_index",
        "min_confidence",
    },
    "delivery": {"kind", "id", "target", "altitude_m", "drop_altitude_m", "speed_mps"},
    "return": {"kind", "id"},
    "parcel": {
        "kind",
        "id",
        "pickup",
        "dropoff",
        "altitude_m",
        "load_altitude_m",
        "load_s",
        "drop_altitude_m",
        "speed_mps",
    },
}
#: The longest a parcel may take to be put on board.
MAX_LOAD_S: Final = 600.0


def _num(raw: Mapping[str, Any], key: str, default: float | None, lo: float, hi: float) -> float:
    value = raw.get(key, default)
    if value is None:
        raise MissionError(f"mission.{key}: required")
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise MissionError(f"mission.{key}: must be a number")
    if not lo <= value <= hi:
        raise MissionError(f"mission.{key}: must be in [{lo:g}, {hi:g}], not {value:g}")
    return float(value)


def _point(value: Any, name: str) -> LatLon:
    if (
        not isinstance(value, list | tuple)
        or len(value) != 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise MissionError(f"{name}: expected [lat, lon] numbers")
    lat, lon = float(value[0]), float(value[1])
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise MissionError(f"{name}: latitude or longitude out of range")
    return (lat, lon)


def mission_parse(raw: Any) -> Mission:
    """Validate the task's ``mission`` object (the contract in docs/rescue-agent.md).

    Raises MissionError naming the field: unknown kind, missing or unknown field
    (missions fail closed, like signed documents), a value out of range, an empty
    path, a start index past its end, a drop altitude not below the cruise altitude.
    """
    if not isinstance(raw, Mapping):
        raise MissionError("mission: must be an object")
    kind = raw.get("kind")
    if kind not in _FIELDS:
        raise MissionError(f"mission.kind: must be one of {', '.join(sorted(_FIELDS))}")
    unknown = set(raw) - _FIELDS[kind]
    if unknown:
        raise MissionError(f"mission: unknown field(s) {', '.join(sorted(unknown))}")
    mission_id = raw.get("id")
    if not isinstance(mission_id, str) or not 0 < len(mission_id) <= 100:
        raise MissionError("mission.id: a non-empty string of at most 100 characters")
    if kind == "return":
        return ReturnMission(id=mission_id)
    altitude = _num(raw, "altitude_m", None, 1.0, MAX_ALTITUDE_M)
    speed = _num(raw, "speed_mps", 10.0, 0.1, MAX_SPEED_MPS)
    if kind == "parcel":
        load = _num(raw, "load_altitude_m", 2.0, 0.5, MAX_ALTITUDE_M)
        drop = _num(raw, "drop_altitude_m", 3.0, 0.5, MAX_ALTITUDE_M)
        if max(load, drop) > altitude:
            raise MissionError("mission: load and drop altitudes must not be above altitude_m")
        return ParcelMission(
            id=mission_id,
            pickup=_point(raw.get("pickup"), "mission.pickup"),
            dropoff=_point(raw.get("dropoff"), "mission.dropoff"),
            altitude_m=altitude,
            load_altitude_m=load,
            load_s=_num(raw, "load_s", 10.0, 0.0, MAX_LOAD_S),
            drop_altitude_m=drop,
            speed_mps=speed,
        )
    if kind == "delivery":
        drop = _num(raw, "drop_altitude_m", 5.0, 0.5, MAX_ALTITUDE_M)
        if drop > altitude:
            raise MissionError("mission.drop_altitude_m: must not be above altitude_m")
        return DeliveryMission(
            id=mission_id,
            target=_point(raw.get("target"), "mission.target"),
            altitude_m=altitude,
            drop_altitude_m=drop,
            speed_mps=speed,
        )
    points = raw.get("waypoints")
    if not isinstance(points, list | tuple) or not 0 < len(points) <= MAX_WAYPOINTS:
        raise MissionError(f"mission.waypoints: a list of 1 to {MAX_WAYPOINTS} [lat, lon]")
    waypoints = tuple(_point(p, f"mission.waypoints[{i}]") for i, p in enumerate(points))
    start = raw.get("start_index", 0)
    if isinstance(start, bool) or not isinstance(start, int) or not 0 <= start < len(waypoints):
        raise MissionError(
            f"mission.start_index: an integer in [0, {len(waypoints) - 1}], not {start!r}"
        )
    return SearchMission(
        id=mission_id,
        altitude_m=altitude,
        speed_mps=speed,
        waypoints=waypoints,
        start_index=start,
        min_confidence=_num(raw, "min_confidence", 0.6, 0.0, 1.0),
    )


class MissionHub(Protocol):
    """What a runner needs from the agent's ControlHub (see its mission_execute)."""

    overrides: int
    override_reason: str
    autonomous: bool

    async def mission_execute(
        self, session_id: str, name: str, args: Mapping[str, Any], *, epoch: int
    ) -> None: ...


class _Interrupted(Exception):
    """Someone else acts on the vehicle (a user, a fail-safe, the autopilot itself): the
    mission ends without sending anything more."""


class _StepFailed(Exception):
    """A step could not be completed (timeout, camera failure): the mission ends and
    the vehicle holds."""


class _Detected(Exception):
    """A person was seen: unwinds the search loop to the detection handling."""

    def __init__(self, blob: Blob, frame: ThermalFrame) -> None:
        super().__init__("person detected")
        self.blob = blob
        self.frame = frame


class MissionRunner:
    """Flies one mission for one session; see the module docstring.

    ``start()`` runs it in a task (after ``previous``, a replaced runner's task, has
    finished cancelling); ``cancel()`` stops it without touching the vehicle (the
    caller decides what the vehicle does next). After it ends, ``result`` holds the
    terminal event reported (``(event, data)``), ``phase`` the last phase.
    ``released`` and ``release_attempted`` are shared with :class:`MissionControl` so a
    payload is never released twice whatever happens to the runner.
    """

    def __init__(
        self,
        mission: Mission,
        *,
        session_id: str,
        hub: MissionHub,
        adapter: Adapter,
        report: Reporter,
        thermal: ThermalFeed | None = None,
        released: dict[str, dict[str, Any]] | None = None,
        release_attempted: set[str] | None = None,
        arrive_m: float = ARRIVE_M,
    ) -> None:
        self.mission = mission
        self.session_id = session_id
        self.hub = hub
        self.adapter = adapter
        self.thermal = thermal
        self.arrive_m = arrive_m
        self.released = released if released is not None else {}
        self.release_attempted = release_attempted if release_attempted is not None else set()
        self._report_fn = report
        self.phase: str | None = None
        self.result: tuple[str, dict[str, Any]] | None = None
        self.last_waypoint: int | None = None
        self.task: asyncio.Task[None] | None = None
        self.cancelled = False
        self._epoch = 0
        self._mode: str | None = None
        self._frame_seq = 0

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
    def _report(self, event: str, **data: Any) -> None:
        payload = {"mission": self.mission.id, **data}
        if event in RESULT_EVENTS or (event == "mission_failed" and self.result is None):
            self.result = (event, payload)
        self._report_fn(event, self.session_id, payload)

    def _where(self) -> dict[str, Any]:
        st = self.adapter.state()
        return {
            "lat": None if st.lat is None else round(st.lat, 7),
            "lon": None if st.lon is None else round(st.lon, 7),
            "alt": None if st.alt is None else round(st.alt, 1),
        }

    def _progress(self, phase: str, waypoint: int | None = None) -> None:
        """A ``mission_progress`` event: on a phase change or a waypoint reached."""
        self.phase = phase
        of = len(self.mission.waypoints) if isinstance(self.mission, SearchMission) else None
        self._report("mission_progress", phase=phase, waypoint=waypoint, of=of, **self._where())

    # --- the run -------------------------------------------------------------------------
    async def _run(self, previous: asyncio.Task[None] | None) -> None:
        if previous is not None:
            await asyncio.wait([previous])  # never raises what ended it
        self._epoch = self.hub.overrides
        self.hub.autonomous = True
        try:
            if isinstance(self.mission, SearchMission):
                await self._search(self.mission)
            elif isinstance(self.mission, ParcelMission):
                await self._parcel(self.mission)
            elif isinstance(self.mission, ReturnMission):
                self._progress("returning")
                await self._command("return_to_home", {})
            else:
                await self._deliver(self.mission)
        except _Interrupted as exc:
            log.warning("mission %s interrupted: %s", self.mission.id, exc)
            self._report("mission_failed", reason=f"interrupted: {exc}")
        except Refusal as exc:
            if exc.code == "no_task":
                return  # the session ended under us: the hub made the vehicle safe
            if exc.code == "overridden":
                self._report("mission_failed", reason=f"interrupted: {exc}")
                return
            self._report("mission_failed", reason=str(exc))
            await self._hold_after_failure()
        except (AdapterError, _StepFailed, ThermalError) as exc:
            log.warning("mission %s failed: %s", self.mission.id, exc)
            self._report("mission_failed", reason=str(exc))
            await self._hold_after_failure()
        except Exception as exc:  # a bug must not end the agent; the vehicle holds
            log.exception("mission %s crashed", self.mission.id)
            self._report("mission_failed", reason=f"internal error: {exc!r}")
            await self._hold_after_failure()
        finally:
            self.hub.autonomous = False

    async def _hold_after_failure(self) -> None:
        """Stop where it is (hover); never raises."""
        try:
            await self.hub.mission_execute(self.session_id, "stop", {}, epoch=self._epoch)
        except (AdapterError, Refusal) as exc:
            log.warning("mission %s: could not hold: %s", self.mission.id, exc)

    async def _command(self, name: str, args: Mapping[str, Any]) -> None:
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

    def _on_surface(self) -> bool:
        """A vehicle that cannot take off (a boat, a car): no climbs, no descents."""
        return not any(c.name == "take_off" for c in self.adapter.commands())

    def _check_interference(self) -> None:
        if self.cancelled:
            # Belt and braces: a cancellation lost in some await must not let a
            # replaced or ended mission fly on.
            raise asyncio.CancelledError
        if self.hub.overrides != self._epoch:
            raise _Interrupted(self.hub.override_reason or "a user command or fail-safe")
        mode = self.adapter.state().mode
        if self._mode is not None and mode is not None and mode != self._mode:
            raise _Interrupted(f"the vehicle switched to {mode} by itself")

    async def _take_off_if_needed(self, altitude: float) -> None:
        if self._on_surface():
            await self._arm_if_needed()
            return
        st = self.adapter.state()
        in_air = self.adapter.telemetry().get("in_air")
        if in_air is None:  # an adapter without the topic: judge by the altitude
            in_air = bool(st.armed) and st.alt is not None and st.alt >= MIN_FLYING_M
        if in_air and st.alt is not None and st.alt >= MIN_FLYING_M:
            return  # already flying
        self._progress("takeoff")
        target = altitude
        if in_air:
            # A take-off is under way (a replaced mission started it): let it clear
            # the ground; the first waypoint sets this mission's altitude.
            target = MIN_FLYING_M + ALTITUDE_TOLERANCE_M
        else:
            await self._command("take_off", {"altitude_m": altitude})
        await self._until(
            lambda s: s.alt is not None and s.alt >= target - ALTITUDE_TOLERANCE_M,
            timeout_s=LEG_MARGIN_S + target / VERTICAL_RATE_MPS,
            what=f"the climb to {target:g} m",
        )

    async def _arm_if_needed(self) -> None:
        """A vehicle on the surface has nothing to take off, but its autopilot drives
        only armed (a boat's ArduRover refuses a waypoint before): arm it. Nothing when
        it is armed already, or has no ``arm`` command (it needs none)."""
        if self.adapter.state().armed or not any(c.name == "arm" for c in self.adapter.commands()):
            return
        await self._command("arm", {})

    async def _fly_to(
        self,
        point: LatLon,
        altitude: float,
        *,
        speed: float,
        detect: float | None = None,
        settle: bool = False,
    ) -> None:
        """go_to_waypoint and wait to be within ``arrive_m`` of it (horizontally);
        ``settle``: and slowed down to a hover there (a pass through the radius at
        cruise speed is not a hold); ``detect``: look for persons at this confidence
        meanwhile (raises _Detected)."""
        st = self.adapter.state()
        here = st.position
        distance = distance_m(here, point) if here is not None else 1000.0
        climb = 0.0 if self._on_surface() else abs(altitude - (st.alt or 0.0))

        def arrived(s: VehicleState) -> bool:
            if s.position is None or distance_m(s.position, point) > self.arrive_m:
                return False
            return not settle or s.speed_mps is None or s.speed_mps <= SETTLED_MPS

        await self._command(
            "go_to_waypoint",
            {"lat": point[0], "lon": point[1], "alt_m": altitude, "speed_mps": speed},
        )
        await self._until(
            arrived,
            timeout_s=LEG_MARGIN_S
            + LEG_TIME_FACTOR * (distance / speed + climb / VERTICAL_RATE_MPS),
            what=f"the flight to {point[0]:.6f}, {point[1]:.6f}",
            detect=detect,
        )

    async def _until(
        self,
        done: Callable[[VehicleState], bool],
        *,
        timeout_s: float,
        what: str,
        detect: float | None = None,
    ) -> None:
        """Wait for ``done(state)``, watching for interference; with ``detect`` the loop
        is paced by the thermal feed and every frame is searched."""
        deadline = time.monotonic() + timeout_s
        while True:
            self._check_interference()
            if done(self.adapter.state()):
                return
            if time.monotonic() > deadline:
                raise _StepFailed(f"{what} did not finish within {timeout_s:.0f} s")
            if detect is not None and self.thermal is not None:
                await self._look(detect)
            else:
                await asyncio.sleep(POLL_S)

    async def _look(self, min_confidence: float) -> None:
        assert self.thermal is not None
        try:
            async with asyncio.timeout(FRAME_TIMEOUT_S):  # not wait_for: see mission_execute
                frame = await self.thermal.frame(newer_than=self._frame_seq)
        except TimeoutError:
            raise ThermalError(f"no thermal frame within {FRAME_TIMEOUT_S:g} s") from None
        self._frame_seq = frame.seq
        for blob in frame.blobs:  # most confident first
            if blob.confidence >= min_confidence:
                raise _Detected(blob, frame)

    # --- search --------------------------------------------------------------------------
    async def _search(self, m: SearchMission) -> None:
        if self.thermal is None:
            raise _StepFailed("this vehicle has no thermal camera (no thermal section)")
        await self._take_off_if_needed(m.altitude_m)
        try:
            for i in range(m.start_index, len(m.waypoints)):
                if i == m.start_index:
                    # Getting to the pattern: no detection until it starts (the way
                    # there may cross a beach full of warm people).
                    self._progress("transit")
                    await self._fly_to(m.waypoints[i], m.altitude_m, speed=m.speed_mps)
                    self.last_waypoint = i
                    self._progress("search", i)
                    # Only frames taken from here on count (the video may have had
                    # the camera running all along).
                    latest = self.thermal.latest
                    self._frame_seq = latest.seq if latest is not None else 0
                    continue
                await self._fly_to(
                    m.waypoints[i],
                    m.altitude_m,
                    speed=m.speed_mps,
                    detect=m.min_confidence,
                    settle=i == len(m.waypoints) - 1,  # it holds at the last one
                )
                self.last_waypoint = i
                self._progress("search", i)
        except _Detected as found:
            await self._found(m, found.blob, found.frame)
            return
        self._report("search_complete", waypoint=self.last_waypoint)
        self._progress("hold", self.last_waypoint)

    async def _found(self, m: SearchMission, blob: Blob, frame: ThermalFrame) -> None:
        assert self.thermal is not None
        lat, lon = geolocate(
            blob, frame.pose, self.thermal.hfov_deg, self.thermal.width, self.thermal.height
        )
        log.info(
            "mission %s: person at %.6f, %.6f (confidence %.2f)",
            m.id,
            lat,
            lon,
            blob.confidence,
        )
        self._report(
            "person_detected",
            lat=round(lat, 7),
            lon=round(lon, 7),
            confidence=round(blob.confidence, 3),
            temperature_c=round(blob.peak_c, 1),
            area_m2=round(blob.area_m2, 3),
            waypoint=self.last_waypoint,
        )
        await self._fly_to((lat, lon), m.altitude_m, speed=m.speed_mps, settle=True)
        self._progress("hold", self.last_waypoint)

    # --- delivery ------------------------------------------------------------------------
    async def _deliver(self, m: DeliveryMission) -> None:
        await self._take_off_if_needed(m.altitude_m)
        self._progress("transit")
        await self._fly_to(m.target, m.altitude_m, speed=m.speed_mps, settle=True)
        self._progress("delivery")
        await self._release_over(m.target, m.id, m.altitude_m, m.drop_altitude_m, m.speed_mps)
        self._progress("hold")

    async def _descend(self, point: LatLon, high: float, low: float, speed: float) -> None:
        """Down to ``low`` over ``point`` (nothing for a vehicle on the surface)."""
        if self._on_surface():
            return
        await self._fly_to(point, low, speed=speed, settle=True)
        await self._until(
            lambda s: s.alt is not None and s.alt <= low + ALTITUDE_TOLERANCE_M,
            timeout_s=LEG_MARGIN_S + (high - low) / VERTICAL_RATE_MPS,
            what=f"the descent to {low:g} m",
        )

    async def _climb(self, point: LatLon, low: float, high: float, speed: float) -> None:
        """Back up to ``high`` over ``point`` (nothing for a vehicle on the surface)."""
        if self._on_surface():
            return
        await self._fly_to(point, high, speed=speed)
        await self._until(
            lambda s: s.alt is not None and s.alt >= high - ALTITUDE_TOLERANCE_M,
            timeout_s=LEG_MARGIN_S + (high - low) / VERTICAL_RATE_MPS,
            what=f"the climb back to {high:g} m",
        )

    async def _release_over(
        self, point: LatLon, mission_id: str, high: float, low: float, speed: float
    ) -> None:
        """Descend over ``point``, release the payload once ever for ``mission_id``
        (``payload_released``), climb back."""
        await self._descend(point, high, low, speed)
        if mission_id in self.release_attempted:
            raise _StepFailed("this mission's payload release was already attempted")
        # Recorded before sending: whatever the answer, it is never sent twice.
        self.release_attempted.add(mission_id)
        await self._command("release_payload", {})
        where = self._where()
        self.released[mission_id] = {
            "mission": mission_id,
            "lat": where["lat"],
            "lon": where["lon"],
        }
        self._report("payload_released", lat=where["lat"], lon=where["lon"])
        await self._climb(point, low, high, speed)

    async def _wait(self, seconds: float) -> None:
        """Stay put for ``seconds``, still watching for interference."""
        until = time.monotonic() + seconds
        await self._until(
            lambda _s: time.monotonic() >= until,
            timeout_s=seconds + LEG_MARGIN_S,
            what=f"a wait of {seconds:g} s",
        )

    # --- parcel --------------------------------------------------------------------------
    async def _parcel(self, m: ParcelMission) -> None:
        await self._take_off_if_needed(m.altitude_m)
        self._progress("to_pickup")
        await self._fly_to(m.pickup, m.altitude_m, speed=m.speed_mps, settle=True)
        self._progress("loading")
        await self._descend(m.pickup, m.altitude_m, m.load_altitude_m, m.speed_mps)
        await self._wait(m.load_s)
        self._report("parcel_loaded", **self._where())
        await self._climb(m.pickup, m.load_altitude_m, m.altitude_m, m.speed_mps)
        self._progress("to_dropoff")
        await self._fly_to(m.dropoff, m.altitude_m, speed=m.speed_mps, settle=True)
        self._progress("delivery")
        await self._release_over(m.dropoff, m.id, m.altitude_m, m.drop_altitude_m, m.speed_mps)
        self._progress("returning")
        await self._command("return_to_home", {})


class MissionControl:
    """The agent's autonomous missions: at most one :class:`MissionRunner`, idempotent
    per mission id. The agent calls :meth:`task_accepted` for every task it accepts
    and :meth:`task_ended` when the hub ends one (before its safe action)."""

    def __init__(
        self,
        *,
        hub: MissionHub,
        adapter: Adapter,
        report: Reporter,
        thermal: ThermalFeed | None = None,
    ) -> None:
        self.hub = hub
        self.adapter = adapter
        self.report = report
        self.thermal = thermal
        self.runner: MissionRunner | None = None
        # Remembered across runners, by mission id: the results of the last REMEMBERED
        # finished missions; payloads released and release attempts for the agent's
        # whole life (a few ids: never forgotten, so never released twice).
        self.results: OrderedDict[str, tuple[str, dict[str, Any]]] = OrderedDict()
        self.released: dict[str, dict[str, Any]] = {}
        self.release_attempted: set[str] = set()

    def task_accepted(self, task: VehicleTask) -> None:
        """Start, keep or replace the runner for ``task.mission`` (None: nothing).

        * a payload already released for this mission id: ``payload_released`` is
          reported again (same position), nothing is flown or released;
        * the running mission has this id: nothing (no restart, no duplicate);
        * a finished mission had this id: its result is reported again;
        * a payload release was attempted for it but never confirmed:
          ``mission_failed``, nothing flies;
        * otherwise a new runner replaces the current one (which stops at once).
        A malformed mission is reported as ``mission_failed`` and changes nothing.
        """
        if task.mission is None:
            return
        claimed = task.mission.get("id")
        try:
            mission = mission_parse(task.mission)
        except MissionError as exc:
            mission_id = claimed if isinstance(claimed, str) and claimed else None
            self.report(
                "mission_failed", task.session_id, {"mission": mission_id, "reason": str(exc)}
            )
            return
        self._remember_finished()
        runner = self.runner
        if mission.id in self.released:
            self.report("payload_released", task.session_id, dict(self.released[mission.id]))
            return
        if runner is not None and runner.mission.id == mission.id and not runner.done:
            return
        if mission.id in self.results:
            event, data = self.results[mission.id]
            self.report(event, task.session_id, dict(data))
            return
        if mission.id in self.release_attempted:
            # Sent once and never confirmed (its runner was stopped mid-command): the
            # payload may be gone, so it is not flown for again.
            reason = "the payload release was attempted already and not confirmed"
            self.report(
                "mission_failed", task.session_id, {"mission": mission.id, "reason": reason}
            )
            return
        previous = None
        if runner is not None:
            runner.cancel()
            previous = runner.task
        self.runner = MissionRunner(
            mission,
            session_id=task.session_id,
            hub=self.hub,
            adapter=self.adapter,
            report=self.report,
            thermal=self.thermal,
            released=self.released,
            release_attempted=self.release_attempted,
        )
        self.runner.start(previous)

    def task_ended(self, task: VehicleTask) -> None:
        """The session ended: its mission stops at once (the hub's safe action follows)."""
        runner = self.runner
        if runner is not None and runner.session_id == task.session_id and not runner.done:
            runner.cancel()

    def _remember_finished(self) -> None:
        runner = self.runner
        if runner is None or not runner.done or runner.result is None:
            return
        self.results[runner.mission.id] = runner.result
        self.results.move_to_end(runner.mission.id)
        while len(self.results) > REMEMBERED:
            self.results.popitem(last=False)

    async def close(self) -> None:
        """Stop the runner (agent shutdown)."""
        if self.runner is not None:
            self.runner.cancel()
            await self.runner.wait()
