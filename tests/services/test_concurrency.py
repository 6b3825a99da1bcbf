"""Under concurrent requests no vehicle is ever reserved twice (real PostgreSQL)."""

from __future__ import annotations

import threading
from collections import Counter

import pytest
from django.db import connection

from fleet.models import Vehicle
from services.assignment import AssignmentError, session_request
from services.models import Assignment, Session
from tests import factories as f

REQUESTS = 40
VEHICLES = 5


@pytest.fixture(autouse=True)
def _online_throughout(settings) -> None:
    """What is tested is the race for rows, not liveness: the vehicles stay online for
    the whole test, however long a loaded machine takes to start its threads (the
    6 s online window passed before the first request on a busy runner)."""
    settings.IOUV_OFFLINE_AFTER_S = 3600


@pytest.mark.postgres
@pytest.mark.django_db(transaction=True)
def test_forty_concurrent_requests_for_five_vehicles():
    st = f.station()
    drone = f.vehicle_type()
    for i in range(VEHICLES):
        f.vehicle(station=st, vtype=drone, name=f"d{i}")
    svc = f.service()
    users = [f.user() for _ in range(REQUESTS)]

    start = threading.Barrier(REQUESTS)
    results: list[str] = []
    refusals: list[str] = []
    crashes: list[BaseException] = []
    lock = threading.Lock()

    def request(user) -> None:
        try:
            start.wait()  # release every thread at once to maximise contention
            session = session_request(user=user, service=svc, target=f.HOME)
            with lock:
                results.append(str(session.pk))
        except AssignmentError as exc:
            with lock:
                refusals.append(str(exc))
        except BaseException as exc:
            with lock:
                crashes.append(exc)
        finally:
            connection.close()  # each thread had its own connection

    threads = [threading.Thread(target=request, args=(u,)) for u in users]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)

    assert not crashes, crashes
    assert len(results) == VEHICLES, set(refusals)
    assert len(refusals) == REQUESTS - VEHICLES
    assert all(reason.startswith("vehicle: ") for reason in refusals)
    held = Counter(Assignment.objects.filter(active=True).values_list("vehicle_id", flat=True))
    assert len(held) == VEHICLES and set(held.values()) == {1}
    assert Vehicle.objects.filter(status=Vehicle.Status.RESERVED).count() == VEHICLES
    assert Session.objects.filter(state=Session.State.ASSIGNED).count() == VEHICLES
    assert Session.objects.filter(state=Session.State.FAILED).count() == REQUESTS - VEHICLES


@pytest.mark.postgres
@pytest.mark.django_db(transaction=True)
def test_one_client_racing_twenty_requests_holds_only_the_services_cap():
    """A client cannot reserve the fleet: its concurrent requests are counted in turn."""
    st = f.station()
    drone = f.vehicle_type()
    for i in range(20):
        f.vehicle(station=st, vtype=drone, name=f"d{i}")
    svc = f.service(max_sessions_per_user=2)
    greedy = f.user()

    start = threading.Barrier(20)
    granted: list[str] = []
    capped: list[str] = []
    crashes: list[BaseException] = []
    lock = threading.Lock()

    def request() -> None:
        try:
            start.wait()
            session = session_request(user=greedy, service=svc, target=f.HOME)
            with lock:
                granted.append(str(session.pk))
        except AssignmentError as exc:
            with lock:
                (capped if exc.over_cap else crashes).append(exc)  # type: ignore[arg-type]
        except BaseException as exc:
            with lock:
                crashes.append(exc)
        finally:
            connection.close()

    threads = [threading.Thread(target=request) for _ in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)

    assert not crashes, crashes
    assert len(granted) == 2 and len(capped) == 18
    assert Vehicle.objects.filter(status=Vehicle.Status.RESERVED).count() == 2
    assert not Session.objects.exclude(pk__in=granted).exists()  # refusals record nothing
