"""Flies the ``survey`` mission: take off if needed, fly the photo lines at the survey's
altitude photographing straight down at each photo's place (``photo_taken``, the picture
kept for the platform as ``photo-<index>.jpg``), then go home (``survey_flown``).

A vehicle whose autopilot flies missions itself (a MAVLink copter) is handed the lines
as one plan (:func:`survey_plan`: the first photo's place, then each line's ends, then
home): the autopilot flies them and comes home even if the agent dies (it takes no
photo then; the platform resumes from the last one it heard of). Otherwise the agent
flies each line's photo places step by step. Either way the pictures are taken by the
agent's photographer, which watches where the vehicle is on the survey's path
(agents.missions.survey.route): a place is photographed when the vehicle is within
:func:`photo_radius_m` of it at the survey's altitude, or, if it went past without
coming that close, as soon as it is seen past it (``late``), unless the vehicle has
left the place's line and is a whole photo spacing away by then: that place is
reported missed (``photo_missed``) and the photographer goes on with the next, so a
slow camera never leaves it behind.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable
from typing import Any, ClassVar, Final, TypeVar

from agents.missions.kit import ALTITUDE_TOLERANCE_M, MissionRunner
from agents.missions.plan import FlightPlan
from agents.missions.spec import LatLon
from agents.missions.survey.route import TRACK_M, Due, PhotoRoute
from agents.missions.survey.spec import SurveySpec

log = logging.getLogger(__name__)

#: How often the photographer checks where the vehicle is.
PHOTO_POLL_S: Final = 0.05
#: After the flight, how long the photographer may take for its last picture.
LAST_PHOTO_S: Final = 10.0

_T = TypeVar("_T")


def photo_name(index: int) -> str:
    """The file name of photo ``index`` (the same on every vehicle of the survey)."""
    return f"photo-{index:04d}.jpg"


def photo_radius_m(spacing_m: float) -> float:
    """How near a photo's place counts as there: a quarter of the spacing, 1 to 3 m."""
    return min(3.0, max(1.0, spacing_m / 4))


def survey_plan(m: SurveySpec, *, speed_mps: float) -> FlightPlan:
    """The survey from photo ``start_photo`` on, as one plan: to the first photo's place
    (``to_area``), along the rest of its line (``surveying``), each following line from
    its start to its end, home (``returning``)."""
    points = m.photo_points()
    first_line, first = points[m.start_photo]
    plan = FlightPlan().take_off(m.altitude_m).speed(speed_mps)
    plan.fly_to(first, m.altitude_m, phase="to_area")
    phase: str | None = "surveying"
    end = m.lines[first_line][1]
    if points[m.start_photo] != points[-1] and end != first:
        plan.fly_to(end, m.altitude_m, phase=phase)
        phase = None
    for start, stop in m.lines[first_line + 1 :]:
        plan.fly_to(start, m.altitude_m, phase=phase)
        phase = None
        if stop != start:
            plan.fly_to(stop, m.altitude_m)
    return plan.return_home()


class SurveyRunner(MissionRunner[SurveySpec]):
    """See the module docstring."""

    RESULT_EVENTS: ClassVar[frozenset[str]] = frozenset({"survey_flown"})

    async def fly(self) -> None:
        m = self.mission
        points = m.photo_points()
        self.progress_of = len(points)
        self.taken = 0
        self.missed: list[int] = []
        self.next_photo = m.start_photo
        speed = self._within_declared("go_to_waypoint", {"speed_mps": m.speed_mps})
        plan = survey_plan(m, speed_mps=float(speed.get("speed_mps", m.speed_mps)))
        if not await self._photographing(self.fly_natively(plan)):
            await self._photographing(self._fly_steps(points))
        self.report(
            "survey_flown", taken=self.taken, of=len(points), missed=self.missed, **self.where()
        )

    async def _fly_steps(self, points: list[tuple[int, LatLon]]) -> bool:
        """The lines flown by the agent, photo place to photo place."""
        m = self.mission
        await self.take_off_if_needed(m.altitude_m)
        self.progress("to_area")
        for index in range(m.start_photo, len(points)):
            if index == m.start_photo + 1:
                self.progress("surveying")
            await self.fly_to(points[index][1], m.altitude_m, speed=m.speed_mps)
        await self.return_home()
        return True

    async def _photographing(self, flight: Awaitable[_T]) -> _T:
        """``flight``, with the photographer watching; the first of them to fail ends
        both. A flight that returns False (the native plan refused) flew nothing: the
        photographer is stopped without a word. Once the return home has begun, the
        photographer settles the places left (photographed late or missed) and stops;
        a camera that takes longer than :data:`LAST_PHOTO_S` for that leaves them
        missed."""
        over = asyncio.Event()
        photographer = asyncio.create_task(self._photographer(over), name="survey photographer")
        flying: asyncio.Future[_T] = asyncio.ensure_future(flight)
        try:
            both: set[asyncio.Future[Any]] = {flying, photographer}
            await asyncio.wait(both, return_when=asyncio.FIRST_COMPLETED)
            if photographer.done() and photographer.exception() is not None:
                raise photographer.exception()  # type: ignore[misc]
            result = await flying
            if result is not False and not photographer.done():
                over.set()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(LAST_PHOTO_S):
                        await asyncio.shield(photographer)
                if not photographer.done():
                    photographer.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await photographer
                    for index in range(self.next_photo, len(self.mission.photo_points())):
                        self._missed(index, "the camera took too long")
            return result
        finally:
            for task in (photographer, flying):
                if not task.done():
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task

    async def _photographer(self, over: asyncio.Event) -> None:
        """Photograph each place from ``start_photo`` on, in order, as the vehicle
        reaches it or, late, passes it; report those it went past too far
        (agents.missions.survey.route). ``over``: the flight is over."""
        m = self.mission
        points = m.photo_points()
        route = PhotoRoute(
            points,
            start=m.start_photo,
            radius_m=photo_radius_m(m.spacing_m),
            late_m=m.spacing_m,
            track_m=max(TRACK_M, m.spacing_m / 2),
        )
        self.next_photo = m.start_photo
        joined = False
        while self.next_photo < len(points):
            index = self.next_photo
            st = self.adapter.state()
            here = st.position
            high = st.alt is not None and st.alt >= m.altitude_m - 2 * ALTITUDE_TOLERANCE_M
            if here is None or not high:
                due = Due.MISSED if over.is_set() else Due.WAIT
            else:
                due = route.due(here, index, joined=joined, over=over.is_set())
            if due is Due.WAIT:
                await asyncio.sleep(PHOTO_POLL_S)
                continue
            if due is Due.MISSED:
                self._missed(index, "the vehicle was past it")
            else:
                meta = await self.photograph(photo_name(index))
                self.taken += 1
                joined = True
                self.report(
                    "photo_taken",
                    index=index,
                    of=len(points),
                    name=photo_name(index),
                    kept=meta["kept"],
                    late=due is Due.LATE,
                    lat=meta["lat"],
                    lon=meta["lon"],
                    alt=meta["alt"],
                    heading_deg=meta["heading_deg"],
                )
            self.next_photo = index + 1

    def _missed(self, index: int, why: str) -> None:
        """Photo ``index`` was not taken (``photo_missed``); the next is due."""
        self.missed.append(index)
        self.next_photo = index + 1
        self.report("photo_missed", index=index, of=self.progress_of, why=why, **self.where())
