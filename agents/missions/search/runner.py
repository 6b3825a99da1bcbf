"""Flies the ``search`` mission: the pattern, the thermal camera watching, the person.

Take off if needed, fly the lawnmower ``waypoints`` from ``start_index`` at
``altitude_m`` while the thermal feed looks for persons; the first blob at
``min_confidence`` or more is reported once (``person_detected``) and the drone flies
over it and holds. No detection: ``search_complete``, hold at the last waypoint.

The camera paces the search, not the clock. Two frames in a row must overlap along the
line (the second taken less than :data:`OVERLAP_FRACTION` of a footprint's length from
the first), or a person between them is never seen. When they do not (a camera, a
detector or a companion computer slower than the speed asked for), the drone slows to
what the frames it gets can cover, flies back to where the last frame was taken and sweeps
the stretch again (``search_slowed``). The distance is measured between the poses the
frames were taken from, so it holds whatever the camera's rate and the flight's clock
(a simulator faster than real time).
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
    footprint_m,
    geolocate,
)

log = logging.getLogger(__name__)

#: The thermal feed must deliver a frame within this long during a search.
FRAME_TIMEOUT_S: Final = 5.0
#: Two frames in a row are taken at most this fraction of a footprint's length apart:
#: a person (well under a metre) and the pose's own error fit in the rest.
OVERLAP_FRACTION: Final = 0.8
#: The slowest a search flies to let its camera keep up. Slower than this and a frame
#: rate that cannot cover the lines is a broken camera, reported, not waited out.
MIN_SEARCH_SPEED_MPS: Final = 1.0


class _Detected(Exception):
    """A person was seen: unwinds the search loop to the detection handling."""

    def __init__(self, blob: Blob, frame: ThermalFrame) -> None:
        super().__init__("person detected")
        self.blob = blob
        self.frame = frame


class _Gap(Exception):
    """Two frames in a row did not overlap: unwinds the leg to sweep the stretch again
    from ``resume_from`` (where the earlier frame was taken) at ``speed_mps``."""

    def __init__(self, resume_from: tuple[float, float], gap_m: float, speed_mps: float) -> None:
        super().__init__(f"{gap_m:.0f} m between frames")
        self.resume_from = resume_from
        self.gap_m = gap_m
        self.speed_mps = speed_mps


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
        #: The speed the lines are flown at: the mission's, lowered when the camera
        #: cannot keep up (never raised again: the camera's rate does not come back
        #: on its own in the middle of a search).
        self.speed_mps = mission.speed_mps
        #: Where the last frame on the current line was taken (None at a line's start).
        self._last_seen: tuple[float, float] | None = None
        self._slowed_at_minimum = False

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
                await self._sweep(m.waypoints[i], settle=i == len(m.waypoints) - 1)
                self.last_waypoint = i
                self.progress("search", i)
        except _Detected as found:
            await self._found(found.blob, found.frame)
            return
        self.report("search_complete", waypoint=self.last_waypoint)
        self.progress("hold", self.last_waypoint)

    async def _sweep(self, end: tuple[float, float], *, settle: bool) -> None:
        """Fly the line to ``end`` looking, sweeping again any stretch two frames did
        not cover (module docstring); ``settle``: hold at its end (the last line)."""
        m = self.mission
        self._last_seen = None  # the turn onto a line is no gap along it
        back: tuple[float, float] | None = None
        while True:
            try:
                if back is not None:
                    await self.fly_to(back, m.altitude_m, speed=self.speed_mps, sample=self._look)
                    back = None
                await self.fly_to(
                    end, m.altitude_m, speed=self.speed_mps, sample=self._look, settle=settle
                )
                return
            except _Gap as gap:
                log.warning(
                    "mission %s: %.0f m between two frames: %.1f m/s from here, and the "
                    "stretch again",
                    m.id,
                    gap.gap_m,
                    gap.speed_mps,
                )
                self.speed_mps = gap.speed_mps
                self.report(
                    "search_slowed",
                    speed_mps=round(gap.speed_mps, 1),
                    gap_m=round(gap.gap_m, 1),
                    **self.where(),
                )
                back = gap.resume_from

    def _covered(self, frame: ThermalFrame) -> None:
        """Raise _Gap when ``frame`` was taken too far from the last one on this line
        to overlap it, with the speed at which the frames would have overlapped."""
        assert self.thermal is not None
        pose = frame.pose
        if pose.lat is None or pose.lon is None or pose.alt is None:
            return
        here, before = (pose.lat, pose.lon), self._last_seen
        self._last_seen = here
        if before is None:
            return
        _, length = footprint_m(pose.alt, self.thermal.hfov_deg, self.thermal.width,
                                self.thermal.height)  # fmt: skip
        reach = OVERLAP_FRACTION * length
        gap = distance_m(before, here)
        if gap <= reach:
            return
        if self.speed_mps <= MIN_SEARCH_SPEED_MPS:
            if not self._slowed_at_minimum:
                self._slowed_at_minimum = True
                log.error(
                    "mission %s: %.0f m between two frames at %.1f m/s: the camera is "
                    "too slow to cover the lines",
                    self.mission.id,
                    gap,
                    self.speed_mps,
                )
            return
        # The frames come as often as they came; at this speed they would be 10 %
        # inside the reach.
        speed = max(MIN_SEARCH_SPEED_MPS, self.speed_mps * 0.9 * reach / gap)
        self._last_seen = before
        raise _Gap(before, gap, speed)

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
        self._covered(frame)

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
        await self.fly_to((lat, lon), m.altitude_m, speed=self.speed_mps, settle=True)
        self.progress("hold", self.last_waypoint)
