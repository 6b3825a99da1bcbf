"""Under concurrent requests no vehicle is ever reserved twice (real PostgreSQL)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
from collections import Counter
from collections.abc import Iterator
from typing import Any

import pytest
from django.conf import settings
from django.db import connection, transaction

from fleet.models import Vehicle
from services.models import Assignment, Session, SessionEvent
from services.sessions.deployment import grant_issue
from services.sessions.log import event_append, session_log, session_log_verify
from services.sessions.matching import AssignmentError
from tests import factories as f
from tests.deployment import session_requested
from tests.servers import ROOT, _test_database_url

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
def test_a_free_vehicle_whose_agent_is_writing_its_row_is_reserved_not_refused():
    """The only matching vehicle is free, but its row is held for a moment by its own
    agent's uplink writing it (a profile, a battery reading): the request waits for the
    write and reserves it, instead of telling the user every vehicle was just taken."""
    car = f.vehicle(station=f.station(), vtype=f.vehicle_type(), name="only")
    svc = f.service()
    written = threading.Event()
    tried = threading.Event()
    crashes: list[BaseException] = []

    def agent_writes() -> None:  # as fleet.uplink stores a profile: lock, write, commit
        try:
            with transaction.atomic():
                Vehicle.objects.select_for_update().get(pk=car.pk)
                Vehicle.objects.filter(pk=car.pk).update(battery=80.0)
                written.set()
                assert tried.wait(60), "the request never tried the vehicle"
        except BaseException as exc:
            crashes.append(exc)
        finally:
            connection.close()

    def spot(execute, sql, params, many, context):  # type: ignore[no-untyped-def]
        result = execute(sql, params, many, context)
        if sql.startswith("UPDATE") and "SKIP LOCKED" in sql:
            tried.set()  # the request found the row held: now the write commits
        return result

    writer = threading.Thread(target=agent_writes)
    writer.start()
    assert written.wait(60)
    with connection.execute_wrapper(spot):
        session = session_requested(user=f.user(), service=svc, target=f.HOME).session
    writer.join(60)

    assert not crashes, crashes
    assert tried.is_set()  # the row was held when the request first tried it
    assert session.state == Session.State.ASSIGNED
    car.refresh_from_db()
    assert car.status == Vehicle.Status.RESERVED and car.battery == 80.0


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


#: A platform process that locks a session's row and then goes silent inside its
#: transaction (a machine cut off from the network): it says "held", and waits on its
#: stdin without another statement; given a line, it tries to commit.
SILENT_HOLDER = """
import sys
import django
django.setup()
from django.db import transaction
from services.models import Session
with transaction.atomic():
    Session.objects.select_for_update(no_key=True).get(pk=sys.argv[1])
    print("held", flush=True)
    sys.stdin.readline()
print("committed", flush=True)
"""


@pytest.mark.postgres
@pytest.mark.django_db(transaction=True)
def test_a_process_gone_silent_in_a_transaction_holds_a_grant_back_only_briefly():
    """A platform process cut off from the network mid-transaction (its machine's link
    cut, as in the two-machine test) never sends another word, and its connection stays
    open. PostgreSQL ends it after ``DB_IDLE_IN_TRANSACTION_S`` and its row lock goes:
    the user's fresh grant, which locks the same session, is answered instead of
    waiting until TCP gives the dead connection up, hours later. The holder is a
    process of its own with the platform's settings."""
    assert settings.DB_IDLE_IN_TRANSACTION_S > 0
    f.vehicle(station=f.station(), vtype=f.vehicle_type(), name="car")
    user = f.user()
    session = session_requested(user=user, service=f.service(), target=f.HOME).session
    env = {
        **{k: v for k, v in os.environ.items() if k != "DB_IDLE_IN_TRANSACTION_S"},
        "DATABASE_URL": _test_database_url(),
        "DJANGO_SETTINGS_MODULE": "iouv.settings",
    }
    holder = subprocess.Popen(
        [sys.executable, "-c", SILENT_HOLDER, str(session.pk)],
        cwd=ROOT,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdin is not None
        assert holder.stdout.readline().strip() == "held", holder.communicate(timeout=60)
        tasks: list[Any] = []

        def grant() -> None:  # waits for the lock, then is answered
            try:
                tasks.append(grant_issue(session=session, user=user))
            finally:
                connection.close()

        granting = threading.Thread(target=grant)
        granting.start()
        granting.join(settings.DB_IDLE_IN_TRANSACTION_S * 6)
        # The holder wakes (at the latest far past the bound, when the grant still
        # waits: then it commits, and the test fails below) and tries to commit.
        out, err = holder.communicate("\n", timeout=60)
        granting.join(60)
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
    assert len(tasks) == 1 and tasks[0].grant
    # The grant came while the silent transaction still held on: its commit found its
    # connection ended by PostgreSQL.
    assert holder.returncode != 0 and "committed" not in out, out
    assert "idle-in-transaction timeout" in err, err[-2000:]
