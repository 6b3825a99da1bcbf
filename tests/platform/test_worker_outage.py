"""The Celery worker and its beat outlive a Redis outage, so the supervision timers run
again once Redis is back.

A real worker with its embedded beat runs on a private redis-server (the machine's
shared one must stay up). The cheapest real timer is fleet's offline sweep: a vehicle
whose heartbeats stopped is marked offline. Redis is killed while the worker holds an
unacknowledged task (the sweep, held up by a lock on the vehicle table: tasks are
acknowledged late), which is the moment a lost connection used to end the worker.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import pytest
from django.db import connection, connections, transaction
from django.utils import timezone

from fleet.models import Vehicle
from tests import factories
from tests.servers import celery_worker_process, db, redis_server_process, until

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


async def test_periodic_timers_run_again_after_a_redis_outage() -> None:
    with (
        redis_server_process() as broker,
        celery_worker_process(
            extra_env={"REDIS_URL": broker.url, "IOUV_OFFLINE_AFTER_S": str(OFFLINE_AFTER_S)}
        ) as worker,
    ):
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
        after = await db(_silent_vehicle, "silent-after-the-outage")
        try:
            await until(lambda: db(_offline, after), within=60, what="a sweep after the outage")
        except AssertionError:
            pytest.fail(
                "no sweep ran after Redis came back; worker "
                f"{'alive' if worker.alive() else 'dead'}:\n{worker.output()}"
            )
        assert worker.alive(), worker.output()
