"""Under concurrent requests no vehicle is ever reserved twice (real PostgreSQL)."""

from __future__ import annotations

import contextlib
import threading
from collections import Counter
from collections.abc import Iterator

import pytest
from django.conf import settings
from django.db import connection, transaction

from fleet.models import Vehicle
from services.models import Assignment, Session, SessionEvent
from services.sessions.log import event_append, session_log, session_log_verify
from services.sessions.matching import AssignmentError
from tests import factories as f
from tests.deployment import session_requested

REQUESTS = 40
VEHICLES = 5


@pytest.fixture(autouse=True)
def _online_throughout(settings) -> None:
    """What is tested is the race for rows, not liveness: the vehicles stay online for
    the whole test, however long a loaded machine takes to start its threads (the
    6 s online window passed before the first request on a busy runner)."""
    settings.IOUV_OFFLINE_AFTER_S = 3600


def _pool_slots() -> threading.BoundedSemaphore:
    """As many threads at once as the process's connection pool lends connections: the
    rest queue here, as requests queue for a pool in production, instead of each
    waiting the pool's short timeout (DB_POOL_TIMEOUT_S, there to answer 503 quickly
    when the database is away) and failing on a loaded machine."""
    pool = settings.DATABASES["default"].get("OPTIONS", {}).get("pool")
    size = pool.get("max_size", REQUESTS) if isinstance(pool, dict) else REQUESTS
    return threading.BoundedSemaphore(max(1, int(size)))


@contextlib.contextmanager
def _pool_filled() -> Iterator[None]:
    """Every connection the pool may lend is open before the threads start: the pool
    otherwise opens them as they are asked for, and a saturated machine takes longer
    than the pool's 1 s timeout to start a PostgreSQL backend."""
    pool = connection.pool  # Django's psycopg_pool for this database (None without one)
    if pool is None:
        yield
        return
    min_size = pool.min_size
    pool.resize(min_size=pool.max_size, max_size=pool.max_size)
    try:
        pool.wait(timeout=60)
        yield
    finally:
        pool.resize(min_size=min_size, max_size=pool.max_size)


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
    connections_lent = _pool_slots()
    results: list[str] = []
    refusals: list[str] = []
    crashes: list[BaseException] = []
    lock = threading.Lock()

    def request(user) -> None:
        try:
            start.wait()  # release every thread at once to maximise contention
            with connections_lent:
                session = session_requested(user=user, service=svc, target=f.HOME).session
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
    with _pool_filled():
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
    connections_lent = _pool_slots()
    granted: list[str] = []
    capped: list[str] = []
    crashes: list[BaseException] = []
    lock = threading.Lock()

    def request() -> None:
        try:
            start.wait()
            with connections_lent:
                session = session_requested(user=greedy, service=svc, target=f.HOME).session
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
    with _pool_filled():
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)

    assert not crashes, crashes
    assert len(granted) == 2 and len(capped) == 18
    assert Vehicle.objects.filter(status=Vehicle.Status.RESERVED).count() == 2
    assert not Session.objects.exclude(pk__in=granted).exists()  # refusals record nothing


@pytest.mark.postgres
@pytest.mark.django_db(transaction=True)
def test_writers_racing_on_one_log_keep_one_chain():
    """Agents' reports append with no lock (two statements each); transactions lock the
    session first, and one reads the whole log to answer with it. Racing on one log,
    every event gets its own place in one unbroken chain, and nobody waits forever on
    anybody (the lock and the reports' inserts cannot deadlock)."""
    f.vehicle(station=f.station(), vtype=f.vehicle_type(), name="v")
    session = session_requested(user=f.user(), service=f.service(), target=f.HOME).session
    before = SessionEvent.objects.filter(session=session).count()
    start = threading.Barrier(12)
    crashes: list[BaseException] = []
    lock = threading.Lock()

    def report(n: int) -> None:  # as the uplink appends an agent's report: no transaction
        for i in range(5):
            event_append(session=session, kind="agent_event", data={"writer": n, "i": i})

    def locked_writer(n: int) -> None:  # appends in a transaction, then locks the row
        for i in range(3):
            with transaction.atomic():
                event_append(session=session, kind="note", data={"writer": n, "i": i})
                Session.objects.select_for_update(no_key=True).get(pk=session.pk)

    def answering_writer(n: int) -> None:  # holds the lock and answers with the log
        for i in range(3):
            with transaction.atomic():
                row = Session.objects.select_for_update(no_key=True).get(pk=session.pk)
                log = session_log(session=row)
                if n % 2:
                    # One of them writes between reading the log and appending, as an end
                    # does (the assignments and the session): a report may take the place
                    # it read as free meanwhile, and the event then follows it, in a
                    # transaction that still commits.
                    Session.objects.filter(pk=row.pk).update(reason=f"writer {n}, note {i}")
                event_append(session=row, kind="note", data={"writer": n, "i": i}, log=log)
            # What it answers with is the whole log, its event last.
            assert [e.seq for e in log] == list(range(1, len(log) + 1))
            assert log[-1].data == {"writer": n, "i": i}

    def run(work, n: int) -> None:  # type: ignore[no-untyped-def]
        try:
            start.wait()
            work(n)
        except BaseException as exc:
            with lock:
                crashes.append(exc)
        finally:
            connection.close()

    workers = [report] * 8 + [locked_writer] * 2 + [answering_writer] * 2
    threads = [threading.Thread(target=run, args=(w, n)) for n, w in enumerate(workers)]
    with _pool_filled():
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)

    assert not crashes, crashes
    events = list(SessionEvent.objects.filter(session=session).order_by("seq"))
    assert len(events) == before + 8 * 5 + 4 * 3
    assert session_log_verify(session=session, events=events).ok
    written = Counter((e.data.get("writer"), e.data.get("i")) for e in events[before:])
    assert set(written.values()) == {1}  # each once: none lost, none written twice
    session.refresh_from_db()
    assert session.reason == "writer 11, note 2"  # the writer's last transaction committed
