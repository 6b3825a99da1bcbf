"""The survey's workflow, with the drone played by its reports and its photos uploaded
through the core's keeper as its agent uploads them: a request checked and refused
naming the field (nothing kept), the grid planned for the drone's camera, the photos
covering the area, a mosaic where every pixel is the ground it shows, its KMZ, a drone
lost mid-way replaced from the first photo not taken, and a cancelled survey."""

from __future__ import annotations

import io
import json
import zipfile
from datetime import timedelta
from typing import Any
from xml.etree import ElementTree

import numpy as np
import pytest
from django.test import Client
from django.urls import reverse
from django.utils import timezone
from PIL import Image

from agents.geo import offset
from agents.missions.survey.spec import SurveySpec
from agents.stills import ground_rgb
from fleet.models import Vehicle
from kinds.survey.geometry import coverage
from kinds.survey.kind import AerialSurvey
from kinds.survey.missions import vehicle_mission
from kinds.survey.models import Survey
from kinds.survey.presentation import survey_json
from kinds.survey.tests.conftest import fly, heard_from, report, spare_drone, surveyor
from kinds.survey.workflow import footprints, survey_advance
from services.kinds import Request, RequestError
from services.models import Service, Session, SessionArtifact
from services.sessions.ending import session_end
from services.sessions.request import service_request
from tests import factories as f

pytestmark = pytest.mark.django_db

CAMPUS = (40.6306, -8.6588)


def field(*corners: tuple[float, float]) -> list[list[float]]:
    """Corners as (north, east) metres from the campus station."""
    return [list(offset(CAMPUS, n, e)) for n, e in corners]


#: A 70 x 50 m field with a slanted side, 100 m north-east of the campus.
FIELD = field((100, 100), (100, 170), (150, 160), (150, 100))


def ask(service: Service, **params: Any) -> Session:
    from django.contrib.auth import get_user_model

    params = {"polygon": FIELD, "gsd_cm": 3, "front_overlap": 75, "side_overlap": 65, **params}
    return service_request(
        user=get_user_model().objects.get(username="client"),
        service=service,
        request=Request(params=params),
    ).session


def survey(session: Session) -> Survey:
    return Survey.objects.get(pk=session.pk)


@pytest.mark.parametrize(
    ("params", "field_name", "words"),
    [
        ({"polygon": field((0, 0), (50, 50), (0, 50), (50, 0))}, "params.polygon", "crosses"),
        ({"gsd_cm": 25}, "params.gsd_cm", "from 0.5 to 20"),
        # 0.6 cm a pixel: quad-1 would fly 4 m up, below the survey's floor.
        ({"gsd_cm": 0.6}, "params.gsd_cm", "quad-1 1.5 to 17.6"),
        # Too far for quad-1's 5 km there and back.
        (
            {"polygon": field((4000, 0), (4000, 60), (4050, 60), (4050, 0))},
            "params.polygon",
            "too far",
        ),
    ],
)
def test_a_survey_no_drone_could_fly_is_refused_naming_the_field_and_nothing_is_kept(
    demo, params, field_name, words
) -> None:
    with pytest.raises(RequestError) as refused:
        ask(demo, **params)
    assert refused.value.field == field_name and words in str(refused.value), str(refused.value)
    assert not Session.objects.exists() and not Survey.objects.exists()


def test_a_request_through_the_api_is_the_same_request(demo) -> None:
    from django.contrib.auth import get_user_model

    from accounts.tokens import token_issue

    token = token_issue(user=get_user_model().objects.get(username="client"), name="tests")

    def post(params: dict[str, Any]) -> Any:
        return Client().post(
            "/api/v1/sessions",
            json.dumps({"service": "aerial-survey", "params": params}),
            content_type="application/json",
            HTTP_AUTHORIZATION=f"Bearer {token}",
        )

    answer = post({"polygon": FIELD, "gsd_cm": 2.5, "side_overlap": 70})
    assert answer.status_code == 201, answer.content
    made = Survey.objects.get(pk=answer.json()["session"]["id"])
    assert (made.gsd_cm, made.front_overlap, made.side_overlap) == (2.5, 0.75, 0.7)
    crossed = post({"polygon": field((0, 0), (50, 50), (0, 50), (50, 0)), "gsd_cm": 3})
    assert crossed.status_code == 400 and crossed.json()["error"]["field"] == "params.polygon"
    assert Survey.objects.count() == 1


def test_the_grid_is_planned_for_the_drones_camera_and_signed_into_its_task(demo) -> None:
    session = ask(demo)
    assert survey(session).state == Survey.State.WAITING_VEHICLE
    assert survey_advance(session.pk) == Survey.State.FLYING
    s = survey(session)
    assert surveyor(session).vehicle.name == "quad-1"
    # quad-1's camera (73.7° over 1024 px) gives 3 cm a pixel 20.5 m up.
    assert s.plan is not None and s.plan["altitude_m"] == pytest.approx(20.49, abs=0.01)
    mission = vehicle_mission(assignment=surveyor(session))
    assert isinstance(mission, SurveySpec) and mission.start_photo == 0
    assert len(mission.photo_points()) == s.photo_count > 10
    assert mission.altitude_m == s.plan["altitude_m"] and mission.speed_mps == 5.0
    assert "quad-1 flies the survey" in s.status_text


def test_the_photos_cover_the_area_and_make_a_mosaic_of_the_ground(demo) -> None:
    session = ask(demo)
    survey_advance(session.pk)
    drone = surveyor(session).vehicle_id
    fly(session)
    s = survey(session)
    assert s.next_photo == s.photo_count
    # Every photo is kept whole, by the core, its digest in the session's log.
    assert SessionArtifact.objects.filter(session=session, stored_at__isnull=False).count() == (
        s.photo_count
    )
    assert session.events.filter(kind="artifact_stored").count() == s.photo_count
    # The photos' footprints cover the area with the asked overlap (as planned).
    polygon = [(p[0], p[1]) for p in FIELD]
    assert coverage(polygon, footprints(s)) >= 0.95
    report(drone, session, "survey_flown", taken=s.photo_count, of=s.photo_count)
    assert survey_advance(session.pk) == Survey.State.DONE
    s = survey(session)
    assert Session.objects.get(pk=session.pk).state == Session.State.ENDED
    assert s.coverage is not None and s.coverage >= 0.95
    assert "covers" in s.status_text
    # The mosaic is the ground where it says it is: sample it inside the field.
    assert s.mosaic is not None
    image = np.asarray(Image.open(io.BytesIO(bytes(s.mosaic))).convert("RGBA"))
    assert s.mosaic_bounds is not None
    south, west, north, east = s.mosaic_bounds
    rows, cols = image.shape[:2]
    rng = np.random.default_rng(7)
    lats = rng.uniform(FIELD[0][0] + 0.00005, FIELD[2][0] - 0.00005, 400)
    lons = rng.uniform(FIELD[0][1] + 0.00005, FIELD[1][1] - 0.0002, 400)
    r = ((north - lats) / (north - south) * rows).astype(int)
    c = ((lons - west) / (east - west) * cols).astype(int)
    shown = image[r, c]
    assert (shown[:, 3] == 255).all()  # photographed everywhere
    truth = ground_rgb(lats, lons).astype(int)
    close = np.abs(shown[:, :3].astype(int) - truth).max(axis=1) <= 40
    # JPEG and the nearest pixel blur hedges and rows a little; the ground is the ground.
    assert close.mean() >= 0.9, close.mean()


def test_the_mosaic_downloads_as_a_kmz_for_its_user_only(demo, client: Client) -> None:
    session = ask(demo)
    survey_advance(session.pk)
    fly(session, range(0, 4))
    report(surveyor(session).vehicle_id, session, "survey_flown", taken=4, of=4)
    s = survey(session)
    Survey.objects.filter(pk=s.pk).update(flown_at=timezone.now() - timedelta(hours=1))
    assert survey_advance(session.pk) == Survey.State.DONE
    assert "photos never came" in survey(session).status_text
    response = client.get(reverse("survey_kmz", args=[session.pk]))
    assert response.status_code == 200
    assert response["Content-Type"] == "application/vnd.google-earth.kmz"
    archive = zipfile.ZipFile(io.BytesIO(response.content))
    assert archive.namelist() == ["doc.kml", "files/mosaic.png"]
    kml = ElementTree.fromstring(archive.read("doc.kml"))
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    box = kml.find(".//k:GroundOverlay/k:LatLonBox", ns)
    assert box is not None
    bounds = survey(session).mosaic_bounds
    assert float(box.findtext("k:north", namespaces=ns) or 0) == pytest.approx(bounds[2])
    assert float(box.findtext("k:west", namespaces=ns) or 0) == pytest.approx(bounds[1])
    Image.open(io.BytesIO(archive.read("files/mosaic.png"))).verify()
    state = client.get(reverse("survey_state", args=[session.pk])).json()
    assert state["mosaic"]["kmz"] == reverse("survey_kmz", args=[session.pk])
    assert len(state["photos"]) == 4 and len(state["photos"][0]["corners"]) == 4
    # Someone else's survey is not theirs to see.
    other = Client()
    other.force_login(f.user(username="mallory"))
    assert other.get(reverse("survey_kmz", args=[session.pk])).status_code in (403, 404)
    assert other.get(reverse("survey_state", args=[session.pk])).status_code in (403, 404)


def test_lines_the_autopilot_refused_are_logged_and_shown_as_flown_place_to_place(demo) -> None:
    """The drone's autopilot refused the lines (agents/missions/kit.py): the log and the
    timeline say so; the survey goes on."""
    session = ask(demo)
    survey_advance(session.pk)
    drone = surveyor(session)
    reason = "the autopilot refused the mission: MAV_MISSION_NO_SPACE (more items than it stores)"
    report(drone.vehicle_id, session, "native_mission_refused", mission="s", reason=reason)
    assert session.events.get(kind="native_mission_refused").data["reason"] == reason
    assert survey_advance(session.pk) == Survey.State.FLYING
    shown = survey_json(survey(session))["timeline"]
    assert [e["data"]["reason"] for e in shown if e["kind"] == "native_mission_refused"] == [reason]


def test_a_drone_lost_mid_way_is_replaced_from_the_first_photo_not_taken(demo, settings) -> None:
    spare = spare_drone("quad-2")
    session = ask(demo)
    survey_advance(session.pk)
    first = surveyor(session)
    fly(session, range(0, 6))
    assert survey(session).next_photo == 6
    lost = timezone.now() - timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S + 1)
    Vehicle.objects.filter(pk=first.vehicle_id).update(
        status=Vehicle.Status.OFFLINE, last_seen=lost
    )
    heard_from(spare)  # while the first drone flew (longer than 6 s on a loaded machine)
    assert survey_advance(session.pk) == Survey.State.FLYING
    second = surveyor(session)
    assert second.vehicle_id == spare.pk
    mission = vehicle_mission(assignment=second)
    assert isinstance(mission, SurveySpec) and mission.start_photo == 6
    # The same grid: the photos' places are the same whichever drone takes them.
    before = vehicle_mission(assignment=first)
    assert before is not None and mission.lines == before.lines
    assert "from photo 7" in survey(session).status_text
    released = session.events.get(kind="vehicle_released").data
    assert released["cause"] == "offline" and released["vehicle_name"] == "quad-1"
    # A late report of the lost drone moves nothing.
    report(first.vehicle_id, session, "photo_taken", index=20)
    assert survey(session).next_photo == 6
    fly(session)
    assert survey(session).next_photo == survey(session).photo_count


def test_a_drone_low_on_battery_hands_over_and_the_next_resumes(demo, settings) -> None:
    spare = spare_drone("quad-2")
    session = ask(demo)
    survey_advance(session.pk)
    first = surveyor(session)
    fly(session, range(0, 9))
    Vehicle.objects.filter(pk=first.vehicle_id).update(
        battery=settings.IOUV_MISSION_LOW_BATTERY_PCT - 1
    )
    heard_from(first.vehicle, spare)  # while the first drone flew
    assert survey_advance(session.pk) == Survey.State.FLYING
    second = surveyor(session)
    assert second.vehicle_id == spare.pk
    mission = vehicle_mission(assignment=second)
    assert isinstance(mission, SurveySpec) and mission.start_photo == 9
    released = session.events.get(kind="vehicle_released").data
    assert "low on battery" in released["reason"]
    # Its photos keep coming after it was released (its agent uploads what it took).
    assert survey(session).legs == 2


def test_the_user_cancels_and_gets_a_mosaic_of_what_came(demo) -> None:
    session = ask(demo)
    survey_advance(session.pk)
    fly(session, range(0, 3))
    session_end(session=session, reason="cancelled by the user", by_user=True)
    assert survey_advance(session.pk) == Survey.State.CANCELLED
    s = survey(session)
    assert "cancelled" in s.status_text and s.mosaic is not None and 0 < (s.coverage or 0) < 0.9


def test_the_demo_offers_the_survey_on_quad_1(demo) -> None:
    assert demo.kind == "survey" and list(demo.roles.values_list("name", flat=True)) == ["surveyor"]
    assert isinstance(AerialSurvey().request_map(demo), dict)
