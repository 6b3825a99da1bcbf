"""Assignment: who gets picked, who is skipped and why, and all-or-nothing roles."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import pytest
from django.utils import timezone

from agents.geo import offset
from fleet.models import Vehicle
from fleet.status import vehicle_set_maintenance
from services.models import Assignment, Session
from services.sessions.matching import AssignmentError
from tests import factories as f
from tests.deployment import session_requested

pytestmark = pytest.mark.django_db


def requested(**request: Any) -> Session:
    """The session a request opens the way the portal does (tests.deployment)."""
    return session_requested(**request).session


@pytest.fixture
def base():
    st = f.station(lat_lon=f.HOME)
    drone = f.vehicle_type("aerial", "mavlink")
    return st, drone


def near(km: float) -> tuple[float, float]:
    """A point ``km`` north of the land station."""
    return offset(f.HOME, km * 1000, 0)


def assigned(session: Session) -> list[str]:
    return [a.vehicle.name for a in session.assignments.filter(active=True)]


def test_picks_the_nearest_eligible_vehicle(base):
    st, drone = base
    f.vehicle(station=st, vtype=drone, name="far", at=near(1.5))
    f.vehicle(station=st, vtype=drone, name="close", at=near(0.2))
    f.vehicle(station=st, vtype=drone, name="middle", at=near(0.8))
    svc = f.service(roles=[{"name": "vehicle", "kinds": ["aerial"]}])

    session = requested(user=f.user(), service=svc, target=near(0.1))

    assert session.state == Session.State.ASSIGNED
    assert assigned(session) == ["close"]
    assert Vehicle.objects.get(name="close").status == Vehicle.Status.RESERVED
    assert Vehicle.objects.get(name="far").status == Vehicle.Status.IDLE


def test_equal_distance_prefers_the_fuller_battery(base):
    st, drone = base
    f.vehicle(station=st, vtype=drone, name="half", battery=50, at=f.HOME)
    f.vehicle(station=st, vtype=drone, name="full", battery=99, at=f.HOME)
    svc = f.service()
    assert assigned(requested(user=f.user(), service=svc, target=near(0.5))) == ["full"]


def test_fastest_selection_prefers_the_first_to_arrive(base):
    st, drone = base
    roomy = {"max_range_m": 20_000, "endurance_min": 60}
    f.vehicle(station=st, vtype=drone, name="slow-near", at=near(0.5), max_speed_mps=2, **roomy)
    f.vehicle(station=st, vtype=drone, name="fast-far", at=near(-0.5), max_speed_mps=20, **roomy)
    svc = f.service(roles=[{"name": "search", "selection": "fastest"}])
    # slow-near: 1.5 km at 2 m/s = 750 s; fast-far: 2.5 km at 20 m/s = 125 s.
    assert assigned(requested(user=f.user(), service=svc, target=near(2))) == ["fast-far"]


@pytest.mark.parametrize(
    ("defect", "role", "reason"),
    [
        ("offline", {}, "no vehicle is online and idle"),
        ("silent", {}, "no vehicle is online and idle"),
        ("busy", {}, "no vehicle is online and idle"),
        ("maintenance", {}, "no vehicle is online and idle"),
        ("low_battery", {"min_battery": 40}, "battery ≥ 40%"),
        ("out_of_range", {}, "reach the target and return"),
        ("wrong_environment", {"environments": ["sea"]}, "operates in sea"),
        ("wrong_camera", {"cameras": ["rgb", "thermal"]}, "cameras rgb + thermal"),
        ("wrong_kind", {"kinds": ["aquatic"]}, "kind aquatic"),
        ("too_light", {"min_attributes": {"max_payload_kg": 1.0}}, "max_payload_kg ≥ 1"),
    ],
)
def test_ineligible_vehicle_is_skipped_and_named_when_alone(base, defect, role, reason):
    st, drone = base
    fine = {"environments": ["air", "sea"], "cameras": ["rgb", "thermal"], "max_payload_kg": 2}
    bad = dict(fine)
    kw: dict = {}
    vtype = drone
    if defect == "offline":
        kw["online"] = False
    elif defect == "busy":
        kw["status"] = Vehicle.Status.IN_SERVICE
    elif defect == "low_battery":
        kw["battery"] = 20
    elif defect == "out_of_range":
        bad["max_range_m"] = 500
    elif defect == "wrong_environment":
        bad["environments"] = ["air", "land"]
    elif defect == "wrong_camera":
        bad["cameras"] = ["rgb"]
    elif defect == "wrong_kind":
        vtype = f.vehicle_type("aerial", "mavlink")
    elif defect == "too_light":
        bad["max_payload_kg"] = 0.5
    flawed = f.vehicle(station=st, vtype=vtype, name="flawed", at=near(0.1), **kw, **bad)
    if defect == "silent":  # status says idle but heartbeats stopped long ago
        Vehicle.objects.filter(pk=flawed.pk).update(last_seen=timezone.now() - timedelta(hours=1))
    if defect == "maintenance":
        vehicle_set_maintenance(vehicle=flawed, on=True)
    role = {"name": "vehicle", **role}
    if defect == "wrong_kind":
        role["kinds"] = ["aquatic"]
    svc = f.service(roles=[role])
    target = near(1.0)

    # Alone, the flawed vehicle is refused with the requirement it missed.
    with pytest.raises(AssignmentError) as refused:
        requested(user=f.user(), service=svc, target=target)
    assert reason in str(refused.value)
    failed = refused.value.session
    assert failed.state == Session.State.FAILED and reason in failed.reason
    assert not Assignment.objects.filter(active=True).exists()

    # With an eligible vehicle farther away, that one is picked instead.
    good_type = f.vehicle_type("aquatic", "mavlink") if defect == "wrong_kind" else drone
    f.vehicle(station=st, vtype=good_type, name="eligible", at=near(1.8), **fine)
    assert assigned(requested(user=f.user(), service=svc, target=target)) == ["eligible"]


def test_a_vehicle_reporting_no_position_is_matched_only_without_a_target(base):
    """A drone before its GPS fix reports no position. A request with a target measures
    the distance, the time to arrive and the range from where the vehicle is, so the
    vehicle is not matched: its station is no stand-in. A request without a target
    measures nothing from it and may have it."""
    st, drone = base
    blind = f.vehicle(station=st, vtype=drone, name="no-fix", at=f.HOME)
    # Its agent reports position null (as the uplink stores it).
    Vehicle.objects.filter(pk=blind.pk).update(lat=None, lon=None, alt=None)
    svc = f.service()
    with pytest.raises(AssignmentError, match="no idle vehicle reports its position"):
        requested(user=f.user(), service=svc, target=near(0.1))
    f.vehicle(station=st, vtype=drone, name="fixed", at=near(1.0))
    assert assigned(requested(user=f.user(), service=svc, target=near(0.1))) == ["fixed"]
    assert assigned(requested(user=f.user(), service=svc)) == ["no-fix"]


def test_all_roles_or_none(base):
    st, drone = base
    f.vehicle(station=st, vtype=drone, name="searcher", cameras=["rgb", "thermal"], at=f.HOME)
    f.vehicle(station=st, vtype=drone, name="light", max_payload_kg=0.5, at=f.HOME)
    svc = f.service(
        roles=[
            {"name": "search", "cameras": ["thermal"]},
            {"name": "delivery", "min_attributes": {"max_payload_kg": 5}},
        ]
    )
    with pytest.raises(AssignmentError, match="delivery: no idle vehicle has max_payload_kg ≥ 5"):
        requested(user=f.user(), service=svc, target=near(0.5))
    # The search vehicle reserved for the first role was given back.
    assert Vehicle.objects.get(name="searcher").status == Vehicle.Status.IDLE
    assert not Assignment.objects.exists()
    assert "max_payload_kg" in Session.objects.get().reason


def test_one_vehicle_fills_only_one_role(base):
    st, drone = base
    f.vehicle(station=st, vtype=drone, name="only")
    svc = f.service(roles=[{"name": "a"}, {"name": "b"}])
    with pytest.raises(AssignmentError, match="b: no vehicle is online and idle"):
        requested(user=f.user(), service=svc)


def test_user_without_grant_is_refused_and_nothing_recorded(base):
    st, drone = base
    f.vehicle(station=st, vtype=drone)
    svc = f.service(grant_clients=False)
    with pytest.raises(AssignmentError, match="may not use"):
        requested(user=f.user(), service=svc)
    assert not Session.objects.exists()
    assert Vehicle.objects.get().status == Vehicle.Status.IDLE


def test_a_reserved_vehicle_is_not_offered_again(base):
    st, drone = base
    f.vehicle(station=st, vtype=drone, name="a", at=near(0.1))
    f.vehicle(station=st, vtype=drone, name="b", at=near(0.3))
    svc = f.service()
    first = requested(user=f.user(), service=svc, target=near(0))
    second = requested(user=f.user(), service=svc, target=near(0))
    assert assigned(first) == ["a"] and assigned(second) == ["b"]
    with pytest.raises(AssignmentError, match="no vehicle is online and idle"):
        requested(user=f.user(), service=svc, target=near(0))


def test_user_preferences_only_narrow_the_choice(base):
    st, drone = base
    f.vehicle(station=st, vtype=drone, name="rgb-near", at=near(0.1))
    f.vehicle(station=st, vtype=drone, name="thermal-far", at=near(1.0), cameras=["rgb", "thermal"])
    svc = f.service()
    chosen = requested(
        user=f.user(), service=svc, target=near(0), preferences={"cameras": ["thermal"]}
    )
    assert assigned(chosen) == ["thermal-far"]
    with pytest.raises(AssignmentError, match="battery ≥ 95%"):
        requested(user=f.user(), service=svc, preferences={"min_battery": 95})


def test_nearest_first_reads_the_fleet_a_page_at_a_time(base, monkeypatch):
    """Matching reads the vehicles nearest the target first, a page at a time: an
    eligible vehicle beyond the first pages is still found, the nearest eligible one
    wins, and when none is eligible the refusal still names the requirement."""
    from services.sessions import matching as assignment

    monkeypatch.setattr(assignment, "POOL_PAGE", 2)
    st, drone = base
    for i in range(1, 4):  # the three nearest are too low on battery
        f.vehicle(station=st, vtype=drone, name=f"low-{i}", battery=5, at=near(0.1 * i))
    f.vehicle(station=st, vtype=drone, name="far-ok", battery=90, at=near(0.9))
    f.vehicle(station=st, vtype=drone, name="ok", battery=90, at=near(0.5))
    svc = f.service(roles=[{"name": "vehicle", "kinds": ["aerial"], "min_battery": 20}])

    assert assigned(requested(user=f.user(), service=svc, target=near(0.0))) == ["ok"]
    assert assigned(requested(user=f.user(), service=svc, target=near(0.0))) == ["far-ok"]
    with pytest.raises(AssignmentError, match="battery"):
        requested(user=f.user(), service=svc, target=near(0.0))
