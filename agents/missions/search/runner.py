"""Flies the ``search`` mission: the pattern, the thermal camera watching, the person.

Take off if needed, fly the lawnmower ``waypoints`` from ``start_index`` at
``altitude_m`` while the thermal feed looks for persons; the first blob at
``min_confidence`` or more is reported once (``person_detected``) and the drone flies
over it and holds. No detection: ``search_complete``, hold at the last waypoint.

The search never outruns its camera: when the drone moved more than half a frame's
footprint (along the track) between two thermal frames (a camera that stalls, a
companion computer too busy to analyse them), a strip of sea between them went unseen,
and the drone slows down until frames overlap again, down to 30 % of the mission's
speed.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, ClassVar, Final

from agents.geo import distance_m
from agents.missions.kit import MissionRunner, StepFailed
from agents.missions.search.spec import SearchSpec
from agents.missions.search.thermal import (
    Blob,
    ThermalError,
    ThermalFeed,
    ThermalFrame,
    ThermalPose,
    footprint_m,
    geolocate,
)
from agents.missions.spec import LatLon

log = logging.getLogger(__name__)

#: The thermal feed must deliver a frame within this long during a search.
FRAME_TIMEOUT_S: Final = 5.0
#: The most ground, as a share of a frame's footprint along the track, the drone may
#: cover between two thermal frames; beyond it the search slows down.
MAX_FRAME_ADVANCE: Final = 0.5
#: The search slows down to no less than this share of the mission's speed (the legs'
#: time limits allow for it).
MIN_SPEED_FACTOR: Final = 0.3


class _Detected(Exception):
    """A person was seen: unwinds the search loop to the detection handling."""

    def __init__(self, blob: Blob, frame: ThermalFrame) -> None:
        super().__init__("person detected")
        self.blob = blob
        self.frame = frame


class SearchRunner(MissionRunner[SearchSpec]):
    """See the module docstring. Needs the agent's ``thermal`` sensor (a
    :class:`~agents.missions.search.thermal.ThermalFeed`); without one the mission fails
    on the ground."""

    RESULT_EVENTS: ClassVar[frozenset[str]] = frozenset(
        {"person_detected", "search_complete", "payload_released"}
    )

    def __init__(self, mission: SearchSpec, **kwargs: Any) -> None:
        super().__init__(mission, **kwargs)
        feed = self.sensors.get("thermal")
        self.thermal: ThermalFeed | None = feed if isinstance(feed, ThermalFeed) else None
        self.progress_of = len(mission.waypoints)
        self.last_waypoint: int | None = None
        self._frame_seq = 0
        self._min_confidence = mission.min_confidence
        self._speed = mission.speed_mps  # lowered when frames stop overlapping
        self._leg: LatLon | None = None  # the waypoint flown to now, while searching
        self._last_pose: ThermalPose | None = None

    async def fly(self) -> None:
        m = self.mission
        if self.thermal is None:
            raise StepFailed("this vehicle has no thermal camera (no thermal section)")
        await self.take_off_if_needed(m.altitude_m)
        try:
            for i in range(m.start_index, len(m.waypoints)):
                if i == m.start_index:
                    # Getting to the pattern: no detection until it starts (the way
                    # there may cross a beach full of warm people).
                    self.progress("transit")
                    await self.fly_to(m.waypoints[i], m.altitude_m, speed=m.speed_mps)
                    self.last_waypoint = i
                    self.progress("search", i)
                    # Only frames taken from here on count (the video may have had
                    # the camera running all along).
                    latest = self.thermal.latest
                    self._frame_seq = latest.seq if latest is not None else 0
                    continue
                self._leg = m.waypoints[i]
                await self.fly_to(
                    m.waypoints[i],
                    m.altitude_m,
                    speed=self._speed,
                    sample=self._look,
                    settle=i == len(m.waypoints) - 1,  # it holds at the last one
                )
                self.last_waypoint = i
                self.progress("search", i)
        except _Detected as found:
            await self._found(found.blob, found.frame)
            return
        self.report("search_complete", waypoint=self.last_waypoint)
        self.progress("hold", self.last_waypoint)

    async def _look(self) -> None:
        """The next thermal frame, searched: raises _Detected on a person at the
        mission's confidence, StepFailed when the camera fails."""
        assert self.thermal is not None
        try:
            async with asyncio.timeout(FRAME_TIMEOUT_S):  # not wait_for: see mission_execute
                frame = await self.thermal.frame(newer_than=self._frame_seq)
        except TimeoutError:
            raise StepFailed(f"no thermal frame within {FRAME_TIMEOUT_S:g} s") from None
        except ThermalError as exc:
            raise StepFailed(str(exc)) from None
        self._frame_seq = frame.seq
        for blob in frame.blobs:  # most confident first
            if blob.confidence >= self._min_confidence:
                raise _Detected(blob, frame)
        await self._keep_overlap(frame.pose)

    async def _keep_overlap(self, pose: ThermalPose) -> None:
        """Slow down when the drone moved too far since the last frame (see the
        module's docstring)."""
        assert self.thermal is not None
        last, self._last_pose = self._last_pose, pose
        if (
            last is None
            or last.lat is None
            or last.lon is None
            or pose.lat is None
            or pose.lon is None
            or not pose.alt
            or self._leg is None
        ):
            return
        moved = distance_m((last.lat, last.lon), (pose.lat, pose.lon))
        camera = self.thermal
        along = footprint_m(pose.alt, camera.hfov_deg, camera.width, camera.height)[1]
        if moved <= MAX_FRAME_ADVANCE * along:
            return
        slower = max(
            self.mission.speed_mps * MIN_SPEED_FACTOR,
            self._speed * MAX_FRAME_ADVANCE * along / moved,
        )
        if slower >= 0.95 * self._speed:
            return  # at the floor already
        log.info(
            "mission %s: %.1f m between thermal frames (footprint %.1f m): slowing to %.1f m/s",
            self.mission.id,
            moved,
            along,
            slower,
        )
        self._speed = slower
        await self.command(
            "go_to_waypoint",
            {
                "lat": self._leg[0],
                "lon": self._leg[1],
                "alt_m": self.mission.altitude_m,
                "speed_mps": slower,
            },
        )

    async def _found(self, blob: Blob, frame: ThermalFrame) -> None:
        assert self.thermal is not None
        m = self.mission
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
        self.report(
            "person_detected",
            lat=round(lat, 7),
            lon=round(lon, 7),
            confidence=round(blob.confidence, 3),
            temperature_c=round(blob.peak_c, 1),
            area_m2=round(blob.area_m2, 3),
            waypoint=self.last_waypoint,
        )
        await self.fly_to((lat, lon), m.altitude_m, speed=m.speed_mps, settle=True)
        self.progress("hold", self.last_waypoint)
