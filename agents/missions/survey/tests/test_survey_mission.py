"""The ``survey`` mission (agents/missions/survey/) flown on the MAVLink simulator: the
autopilot flies the photo lines itself, the agent photographs each place straight down
and keeps the geotagged pictures for the platform; a survey resumes at a photo; with
the agent dead, the autopilot comes home by itself."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any, cast

import pytest

from agents.geo import distance_m, local_offset_m, offset
from agents.missions.registry import mission_decode
from agents.missions.spec import MissionError
from agents.missions.survey.runner import photo_name, photo_radius_m, survey_plan
from agents.missions.survey.spec import SurveySpec
from agents.missions.survey.tests.conftest import SurveyRigFactory, photos
from agents.stills import NadirSimCamera, Photo
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.plan import ReturnHome, Waypoint
from tests.agents.geotags import photo_position
from tests.agents.mission_rig import (
    HOME,
    SIM,
    Rig,
    agent_dies,
    landed_at_home,
    last_position,
    listen,
    make_task,
    texts,
)

#: Three lines of 40 m, 12 m apart, 30 m north-east of home: 5 photos each at 10 m.
LINES = [
    [offset(HOME, 30, 20), offset(HOME, 30, 60)],
    [offset(HOME, 42, 60), offset(HOME, 42, 20)],
    [offset(HOME, 54, 20), offset(HOME, 54, 60)],
]


def survey(mission_id: str = "m-survey", **overrides: Any) -> dict[str, Any]:
    return {
        "kind": "survey",
        "id": mission_id,
        "lines": [[list(a), list(b)] for a, b in LINES],
        "spacing_m": 10,
        "altitude_m": 20,
        "speed_mps": 4,
        "start_photo": 0,
        **overrides,
    }


async def until(done: Callable[[], bool], *, within: float, what: str = "") -> None:
    deadline = time.monotonic() + within
    while not done():
        assert time.monotonic() < deadline, f"not reached in time: {what}"
        await asyncio.sleep(0.05)


def test_a_survey_is_validated_and_its_photos_are_placed_evenly() -> None:
    spec = mission_decode(survey())
    assert isinstance(spec, SurveySpec) and spec.to_payload() == {
        **survey(),
        "lines": [[list(a), list(b)] for a, b in LINES],
    }
    points = spec.photo_points()
    assert len(points) == 15 and [line for line, _ in points] == [0] * 5 + [1] * 5 + [2] * 5
    gaps = [distance_m(points[i][1], points[i + 1][1]) for i in range(4)]
    assert gaps == pytest.approx([10.0] * 4, abs=0.05)
    with pytest.raises(MissionError, match=r"mission\.start_photo: an integer in \[0, 14\]"):
        mission_decode(survey(start_photo=15))
    with pytest.raises(MissionError, match=r"mission\.spacing_m: makes .* photos; at most 2000"):
        mission_decode(survey(spacing_m=0.5, lines=[[list(HOME), list(offset(HOME, 0, 999))]] * 3))
    with pytest.raises(MissionError, match=r"mission\.lines"):
        mission_decode(survey(lines=[]))
    with pytest.raises(MissionError, match=r"mission\.altitude_m"):
        mission_decode(survey(altitude_m=900))


def test_the_plan_is_the_first_place_then_each_lines_ends_then_home() -> None:
    plan = survey_plan(mission_decode(survey(start_photo=7)), speed_mps=4)  # type: ignore[arg-type]
    ways = [s.item.point for s in plan.steps if isinstance(s.item, Waypoint)]
    # Photo 7 is the middle of line 1 (flown east to west): from there to its end.
    assert distance_m(ways[0], offset(HOME, 42, 40)) < 0.01
    assert ways[1:] == [LINES[1][1], LINES[2][0], LINES[2][1]]
    assert isinstance(plan.steps[-1].item, ReturnHome)
    assert [s.phase for s in plan.steps if s.phase] == ["to_area", "surveying", "returning"]


def photos_taken(rig: Rig) -> list[dict[str, Any]]:
    return [d for _, d in rig.events("photo_taken")]


async def test_the_autopilot_flies_the_lines_and_each_place_is_photographed_straight_down(
    make_survey_rig: SurveyRigFactory,
) -> None:
    rig = await make_survey_rig()
    rig.accept(make_task(survey()))
    flown = await rig.event("survey_flown", within=240)
    assert rig.drone.state().mode in ("AUTO", "RTL")  # the autopilot's own mission
    assert flown["taken"] == flown["of"] == 15
    taken = photos_taken(rig)
    assert [d["index"] for d in taken] == list(range(15)) and all(d["kept"] for d in taken)
    spec = mission_decode(survey())
    assert isinstance(spec, SurveySpec)
    places = spec.photo_points()
    for photo in taken:
        # Where it was taken: at the place, or seen past it late, within two spacings
        # (one and a half seen with the suite's other workers busy).
        place = places[photo["index"]][1]
        off = distance_m((photo["lat"], photo["lon"]), place)
        assert off < (2 * spec.spacing_m if photo["late"] else photo_radius_m(10) + 1), photo
        assert photo["alt"] == pytest.approx(20, abs=2.5)
    files = photos(rig)
    assert [p.name for p in files] == [f"photo-{i:04d}.jpg" for i in range(15)]
    for path, photo in zip(files, taken, strict=True):
        tagged = photo_position(path.read_bytes())
        assert tagged is not None and distance_m(tagged, (photo["lat"], photo["lon"])) < 0.01
    phases = [p for p, _ in rig.progress()]
    assert phases.index("to_area") < phases.index("surveying") < phases.index("returning")
    await until(lambda: not rig.drone.state().armed, within=120, what="landed at home")
    here = rig.drone.state().position
    assert here is not None and distance_m(here, HOME) < 3


async def test_a_survey_resumes_at_the_photo_it_is_told(
    make_survey_rig: SurveyRigFactory,
) -> None:
    rig = await make_survey_rig()
    rig.accept(make_task(survey("m-resumed", start_photo=8)))
    flown = await rig.event("survey_flown", within=240)
    assert flown["taken"] == 7
    assert [d["index"] for d in photos_taken(rig)] == list(range(8, 15))
    assert [p.name for p in photos(rig)] == [f"photo-{i:04d}.jpg" for i in range(8, 15)]


async def test_without_native_missions_the_agent_flies_each_place(
    make_survey_rig: SurveyRigFactory,
) -> None:
    rig = await make_survey_rig(native_missions=False)
    rig.accept(make_task(survey("m-steps", start_photo=10)))
    flown = await rig.event("survey_flown", within=240)
    assert flown["taken"] == 5 and [d["index"] for d in photos_taken(rig)] == list(range(10, 15))
    assert rig.drone.state().mode != "AUTO"


async def test_when_the_agent_dies_mid_survey_the_autopilot_comes_home_and_lands(
    make_survey_rig: SurveyRigFactory,
) -> None:
    params = {**cast(dict[str, Any], SIM["params"]), "FS_GCS_TIMEOUT": 2, "FS_OPTIONS": 0}
    rig = await make_survey_rig(simulator={**SIM, "params": params})
    rig.accept(make_task(survey("m-dies")))
    await until(lambda: len(photos_taken(rig)) >= 3, within=120, what="three photos")
    address = await agent_dies(rig)
    heard = await listen(address, landed_at_home, within=180)
    assert "GCS Failsafe" in texts(heard)
    assert distance_m(last_position(heard), HOME) < 3


class HeldCamera:
    """The nadir camera, but its ``hold``-th picture (0 first) comes only once the drone
    is ``past_m`` along line 1 (flown westwards at 42 m north): a camera so slow that
    the drone rounds the end of line 0 during it."""

    def __init__(
        self, camera: NadirSimCamera, drone: MavlinkAdapter, *, hold: int, past_m: float
    ) -> None:
        self.camera = camera
        self.drone = drone
        self.hold = hold
        self.past_m = past_m
        self.hfov_deg, self.width, self.height = camera.hfov_deg, camera.width, camera.height
        self.count = 0

    def on_line_1(self) -> bool:
        here = self.drone.state().position
        if here is None:
            return False
        north, east = local_offset_m(HOME, here)
        return abs(north - 42) < 2 and east < 60 - self.past_m

    async def capture(self, pose: Any) -> Photo:
        photo = await self.camera.capture(pose)
        self.count += 1
        if self.count - 1 == self.hold:
            await until(self.on_line_1, within=120, what="the drone on line 1")
        return photo


async def test_a_place_passed_during_a_slow_picture_is_missed_and_the_rest_are_taken(
    make_survey_rig: SurveyRigFactory,
) -> None:
    """Photo 3 takes until the drone is 4 m along line 1: photo 4 (line 0's end) is 13 m
    behind by then, missed; photo 5 (line 1's start, 4 m behind) is taken late; the
    photographer never waits for a place the autopilot has left."""
    rig = await make_survey_rig(
        camera=lambda nadir, drone: HeldCamera(nadir, drone, hold=3, past_m=4)
    )
    rig.accept(make_task(survey("m-held")))
    flown = await rig.event("survey_flown", within=240)
    assert flown["missed"] == [4] and flown["taken"] == 14 and flown["of"] == 15
    missed = [d for _, d in rig.events("photo_missed")]
    assert [d["index"] for d in missed] == [4] and missed[0]["why"] == "the vehicle was past it"
    taken = {d["index"]: d for d in photos_taken(rig)}
    assert sorted(taken) == [0, 1, 2, 3, *range(5, 15)]
    # Photo 5 is late; the next ones are taken too (on a busy machine they may be a
    # little late as well: the photographer polls the position on the wall clock).
    assert taken[5]["late"]
    assert distance_m((taken[5]["lat"], taken[5]["lon"]), offset(HOME, 42, 60)) < 10
    assert [p.name for p in photos(rig)] == [photo_name(i) for i in sorted(taken)]
