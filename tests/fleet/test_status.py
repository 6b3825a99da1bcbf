"""Live status: silent vehicles go offline; maintenance in and out."""

from __future__ import annotations

from datetime import timedelta

import pytest
from django.utils import timezone

from agents.protocol.messages import Heartbeat, Position
from fleet.models import Vehicle
from fleet.status import FleetError, vehicle_set_maintenance, vehicles_online
from fleet.tasks import fleet_sweep_offline
from tests import factories as f

pytestmark = pytest.mark.django_db


def test_sweep_marks_only_silent_vehicles_offline(settings):
    settings.IOUV_OFFLINE_AFTER_S = 5
    st, vt = f.station(), f.vehicle_type()
    alive = f.vehicle(station=st, vtype=vt, name="alive")
    silent = f.vehicle(station=st, vtype=vt, name="silent")
    Vehicle.objects.filter(pk=silent.pk).update(last_seen=timezone.now() - timedelta(seconds=6))

    assert fleet_sweep_offline.apply().get() == 1
    assert Vehicle.objects.get(pk=silent.pk).status == Vehicle.Status.OFFLINE
    assert Vehicle.objects.get(pk=alive.pk).status == Vehicle.Status.IDLE
    assert list(vehicles_online()) == [alive]


def test_maintenance_in_and_out():
    v = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    vehicle_set_maintenance(vehicle=v, on=True)
    v.refresh_from_db()
    assert v.status == Vehicle.Status.MAINTENANCE and v.maintenance
    assert not vehicles_online().exists()
    vehicle_set_maintenance(vehicle=v, on=False)
    v.refresh_from_db()
    assert v.status == Vehicle.Status.IDLE and not v.maintenance


def test_maintenance_refused_for_a_vehicle_in_a_session():
    v = f.vehicle(station=f.station(), vtype=f.vehicle_type(), status=Vehicle.Status.IN_SERVICE)
    with pytest.raises(FleetError, match="end its session first"):
        vehicle_set_maintenance(vehicle=v, on=True)
    v.refresh_from_db()
    assert not v.maintenance


def test_a_vehicle_still_flying_home_is_not_assignable_until_it_says_idle():
    from fleet.uplink import HeartbeatReport, vehicle_record_heartbeats

    v = f.vehicle(station=f.station(), vtype=f.vehicle_type())
    beat = Heartbeat(seq=1, status="returning")
    vehicle_record_heartbeats([HeartbeatReport(str(v.pk), beat, timezone.now(), True)])
    v.refresh_from_db()
    assert v.status == Vehicle.Status.RETURNING
    assert not vehicles_online().filter(status=Vehicle.Status.IDLE).exists()

    beat = Heartbeat(seq=2, status="idle")
    later = timezone.now() + timedelta(seconds=5)  # past the heartbeat write throttle
    vehicle_record_heartbeats([HeartbeatReport(str(v.pk), beat, later, True)])
    v.refresh_from_db()
    assert v.status == Vehicle.Status.IDLE


def test_heartbeats_of_many_vehicles_in_one_write():
    from fleet.uplink import HeartbeatReport, vehicle_record_heartbeats

    station, vtype = f.station(), f.vehicle_type()
    idle = f.vehicle(station=station, vtype=vtype, battery=90)
    held = f.vehicle(station=station, vtype=vtype, status=Vehicle.Status.IN_SERVICE)
    offline = f.vehicle(station=station, vtype=vtype, status=Vehicle.Status.OFFLINE)
    now = timezone.now()
    beats = [
        HeartbeatReport(str(idle.pk), Heartbeat(seq=1, battery=80), now, True),
        # A vehicle's later heartbeat in the same batch wins.
        HeartbeatReport(str(idle.pk), Heartbeat(seq=2, battery=79), now, True),
        HeartbeatReport(str(held.pk), Heartbeat(seq=1, status="idle"), now, True),
        HeartbeatReport(
            str(offline.pk), Heartbeat(seq=1, position=Position(lat=40.1, lon=-8.2)), now, True
        ),
        HeartbeatReport("0" * 32, Heartbeat(seq=1), now, True),  # deleted meanwhile
    ]
    written = vehicle_record_heartbeats(beats)
    assert sorted(written) == sorted(str(v.pk) for v in (idle, held, offline))
    for v in (idle, held, offline):
        v.refresh_from_db()
        assert v.last_seen == now
    assert (idle.battery, idle.status) == (79, Vehicle.Status.IDLE)
    # The platform's statuses are its own; what the agent says does not override them.
    assert held.status == Vehicle.Status.IN_SERVICE
    # Heard from again: back in the pool, where it says it is; its battery unchanged.
    assert (offline.status, offline.lat, offline.lon) == (Vehicle.Status.IDLE, 40.1, -8.2)
    assert offline.battery == 90.0
