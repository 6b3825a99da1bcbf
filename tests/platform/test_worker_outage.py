"""The supervision timers run again after a Redis outage, with the Celery worker run as
its unit runs it.

A real worker with its embedded beat runs on a private redis-server (the machine's
shared one must stay up). The cheapest real timer is fleet's offline sweep: a vehicle
whose heartbeats stopped is marked offline. Redis is killed while the worker holds an
unacknowledged task (the sweep, held up by a lock on the vehicle table: tasks are
acknowledged late). That is the moment kombu's Redis transport fails to close the dead
connection (``AttributeError: 'NoneType' object has no attribute 'hostname'``, which
Celery reports as an unrecoverable error) and the worker exits: it must exit rather
than hang, and its unit (``Restart=always``) starts it again.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import threading
from collections.abc import AsyncIterator, Iterator
from datetime import timedelta
from typing import Any

import pytest
from django.db import connection, connections, transaction
from django.utils import timezone

from fleet.models import Vehicle
from tests import factories
from tests.servers import ROOT, celery_worker_process, db, redis_server_process, until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]

#: How long Redis stays away: a restart, a failover, a brief network loss.
OUTAGE_S = 3.0
#: Sweeps run every OFFLINE_AFTER_S / 2 seconds: one is due soon, but they are far
#: enough apart that the first one is alone in the worker when Redis goes away.
OFFLINE_AFTER_S = 8


def _silent_vehicle(name: str) -> Any:
    """An idle vehicle whose last heartbeat is an hour old: the next sweep takes it."""
    vehicle = factories.vehicle(
        station=factories.station(), vtype=factories.vehicle_type(), name=name
    )
    Vehicle.objects.filter(pk=vehicle.pk).update(last_seen=timezone.now() - timedelta(hours=1))
    return vehicle.pk


def _offline(pk: Any) -> bool:
    return Vehicle.objects.get(pk=pk).status == Vehicle.Status.OFFLINE


def _sweep_waiting_for_the_lock() -> bool:
    """True once another session (the worker's sweep) waits for a lock on the vehicle
    table of this database."""
    with connection.cursor() as cursor:
        cursor.execute(
            """
            SELECT count(*) FROM pg_locks l JOIN pg_class c ON c.oid = l.relation
            WHERE c.relname = 'fleet_vehicle' AND NOT l.granted
              AND l.database = (SELECT oid FROM pg_database WHERE datname = current_database())
            """
        )
        return bool(cursor.fetchone()[0])


@contextlib.contextmanager
def vehicle_table_locked() -> Iterator[None]:
    """Hold the vehicle table in EXCLUSIVE mode on a connection of its own: plain reads
    go on, the sweep's ``SELECT ... FOR UPDATE`` waits until the block is left."""
    locked, release = threading.Event(), threading.Event()
    failed: list[BaseException] = []

    def hold() -> None:
        try:
            with transaction.atomic(), connection.cursor() as cursor:
                cursor.execute("LOCK TABLE fleet_vehicle IN EXCLUSIVE MODE")
                locked.set()
                release.wait(120)
        except BaseException as exc:  # reported to the test below
            failed.append(exc)
            locked.set()
        finally:
            connections.close_all()

    holder = threading.Thread(target=hold, name="vehicle-table-lock")
    holder.start()
    try:
        if not locked.wait(10) or failed:
            raise RuntimeError(f"could not lock the vehicle table: {failed}")
        yield
    finally:
        release.set()
        holder.join(timeout=30)


#: The worker's unit, as deploy/ ships it.
WORKER_UNIT = ROOT / "deploy" / "systemd" / "iouv-worker.service"


def _unit_setting(name: str) -> str:
    found = re.search(rf"^{name}=(.*)$", WORKER_UNIT.read_text(), re.MULTILINE)
    assert found, f"{WORKER_UNIT.name} sets no {name}"
    return found.group(1).strip()


@contextlib.asynccontextmanager
async def supervised(worker: Any) -> AsyncIterator[list[str]]:
    """Start ``worker`` again whenever it exits, ``RestartSec`` later, as systemd does
    with the unit's ``Restart=always``; yields the end of the output of each run that
    ended."""
    assert _unit_setting("Restart") == "always"
    restart_s = float(_unit_setting("RestartSec"))
    ended: list[str] = []

    async def watch() -> None:
        while True:
            await asyncio.sleep(0.2)
            if not worker.alive():
                ended.append(worker.output())
                worker.kill()  # closes the ended run's log
                await asyncio.sleep(restart_s)
                worker.start()

    watcher = asyncio.create_task(watch())
    try:
        yield ended
    finally:
        watcher.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await watcher


async def _outage_under_a_busy_worker(broker: Any, worker: Any) -> None:
    """Sweep once, then take Redis away for OUTAGE_S while the worker holds a sweep
    waiting for the vehicle table, and bring it back; returns once that sweep ran."""
    before = await db(_silent_vehicle, "silent-before-the-outage")
    await until(lambda: db(_offline, before), within=30, what="the sweep before the outage")

    # The sweep locks only the rows it found silent: give it one to lock.
    during = await db(_silent_vehicle, "silent-during-the-outage")
    with vehicle_table_locked():

        async def sweep_alone_and_waiting() -> bool:
            # Between two bursts of timers, with nothing else in flight: Redis
            # goes away while the worker holds exactly one unacknowledged task.
            return (
                worker.tasks_in_flight() == ["fleet.sweep_offline"]
                and worker.quiet_for() > 0.3
                and await db(_sweep_waiting_for_the_lock)
            )

        await until(
            sweep_alone_and_waiting,
            within=30,
            what="a sweep in the worker, alone, waiting for the vehicle table",
        )
        broker.kill()
        await asyncio.sleep(OUTAGE_S)  # the outage itself, not a wait for a result
        broker.start()

    await until(lambda: db(_offline, during), within=60, what="the sweep held up")


async def test_periodic_timers_run_again_after_a_redis_outage(record_property: Any) -> None:
    with (
        redis_server_process() as broker,
        celery_worker_process(
            extra_env={"REDIS_URL": broker.url, "IOUV_OFFLINE_AFTER_S": str(OFFLINE_AFTER_S)}
        ) as worker,
    ):
        async with supervised(worker) as ended:
            await _outage_under_a_busy_worker(broker, worker)
            after = await db(_silent_vehicle, "silent-after-the-outage")
            try:
                await until(lambda: db(_offline, after), within=60, what="a sweep after the outage")
            except AssertionError:
                runs = "\n---\n".join([*ended, worker.output()])
                pytest.fail(f"no sweep ran after Redis came back; the worker's runs:\n{runs}")
        record_property("worker_runs_ended_by_the_outage", len(ended))
