"""What operators watch: ``/metrics`` for Prometheus (prometheus-client).

Read from the database and the broker when Prometheus scrapes, the same from any
platform process:

* ``iouv_agents_online``: vehicles whose agent is connected (not offline, not in
  maintenance), and ``iouv_vehicles{status}`` by status;
* ``iouv_sessions{state}``: live sessions by state (requested, assigned, active);
* ``iouv_outbox_backlog`` and ``iouv_outbox_oldest_age_seconds``: what the platform owes
  agents and has not had acknowledged (fleet.outbox), and how long the oldest has waited;
* ``iouv_celery_queue_length{queue}``: tasks waiting for a worker;
* ``iouv_celery_task_failures_total{task}``: tasks that raised, counted by the workers
  in Django's cache (Redis with ``REDIS_URL``) and read here.

Counted by the process that sees them (the relay runs in the processes serving
WebSockets):

* ``iouv_relay_commands_acked_total{ok}``: relayed commands the vehicle acknowledged,
  accepted (``ok="true"``) or refused;
* ``iouv_relay_round_trip_seconds``: from a relayed command reaching the platform to the
  vehicle's acknowledgement leaving it (histogram).

Several processes on one machine share their counts when ``PROMETHEUS_MULTIPROC_DIR``
names a folder they all write (prometheus-client's multiprocess mode; empty it when the
processes start); otherwise each process answers for itself and Prometheus scrapes each.

Access: with ``IOUV_METRICS_TOKEN`` set, ``Authorization: Bearer <token>``; without it,
only clients on the platform's own machine (loopback). Anyone else gets a 404.
"""

from __future__ import annotations

import functools
import hmac
import ipaddress
import logging
import os
import time
from collections.abc import Iterator
from typing import Any

from django.conf import settings
from django.core.cache import cache
from django.db.models import Count, Min
from django.http import Http404, HttpRequest, HttpResponse
from django.utils import timezone
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
    multiprocess,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from accounts.addresses import client_address
from fleet.models import AgentMessage, Vehicle
from fleet.status import vehicles_online
from services.models import Session
from services.sessions.states import FINAL

log = logging.getLogger(__name__)

RELAY_ACKS = Counter(
    "iouv_relay_commands_acked",
    "Relayed commands the vehicle acknowledged (ok: accepted, else refused).",
    ["ok"],
)
RELAY_ROUND_TRIP = Histogram(
    "iouv_relay_round_trip_seconds",
    "A relayed command's round trip through the platform: from the browser's command "
    "reaching it to the vehicle's acknowledgement leaving it.",
    buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0),
)

#: The cache key of a Celery task's failures (counted by the workers).
_FAILURES_KEY = "iouv:metrics:task_failures:{}"


def celery_task_failed(sender: Any = None, **kwargs: Any) -> None:
    """Celery's ``task_failure`` signal (connected in services.apps): one more failure
    of the task, in Django's cache, where every worker counts and ``/metrics`` reads."""
    name = getattr(sender, "name", None) or "unknown"
    key = _FAILURES_KEY.format(name)
    try:
        cache.add(key, 0, timeout=None)
        cache.incr(key)
    except Exception as exc:  # the cache away: a failure uncounted, not a second one
        log.warning("task %s failed and could not be counted: %s", name, exc)


@functools.cache
def _celery_task_names() -> list[str]:
    """Every task of the platform (the workers' ``tasks.py`` modules, imported here
    once as a worker imports them)."""
    from iouv.celery import app

    app.autodiscover_tasks(force=True)
    return sorted(name for name in app.tasks if not name.startswith("celery."))


def _celery_queue_lengths() -> dict[str, int]:
    """Tasks waiting in each queue the workers consume (the broker's own count)."""
    from iouv.celery import app

    queues = {queue.name for queue in app.amqp.queues.values()} or {"celery"}
    lengths: dict[str, int] = {}
    with app.connection_for_read() as connection:
        channel: Any = connection.default_channel  # kombu's channel: queue_declare
        for name in sorted(queues):
            # Declared as every producer of a task declares it (a queue nobody has
            # used yet has no messages), then counted by the broker.
            lengths[name] = channel.queue_declare(queue=name).message_count
    return lengths


class PlatformCollector(Collector):
    """The gauges read from the database and the broker at each scrape."""

    def collect(self) -> Iterator[Any]:
        online = GaugeMetricFamily("iouv_agents_online", "Vehicles whose agent is connected.")
        online.add_metric([], vehicles_online().count())
        yield online

        vehicles = GaugeMetricFamily("iouv_vehicles", "Vehicles by status.", labels=["status"])
        counts = dict(
            Vehicle.objects.values_list("status").annotate(n=Count("pk")).values_list("status", "n")
        )
        for status in Vehicle.Status.values:
            vehicles.add_metric([status], counts.get(status, 0))
        yield vehicles

        sessions = GaugeMetricFamily("iouv_sessions", "Live sessions by state.", labels=["state"])
        live = [state for state in Session.State.values if state not in FINAL]
        counts = dict(
            Session.objects.filter(state__in=live)
            .values_list("state")
            .annotate(n=Count("pk"))
            .values_list("state", "n")
        )
        for state in live:
            sessions.add_metric([state], counts.get(state, 0))
        yield sessions

        owed = AgentMessage.objects.filter(state=AgentMessage.State.PENDING).aggregate(
            n=Count("pk"), oldest=Min("created_at")
        )
        backlog = GaugeMetricFamily(
            "iouv_outbox_backlog", "Messages owed to agents and not yet acknowledged."
        )
        backlog.add_metric([], owed["n"])
        yield backlog
        age = GaugeMetricFamily(
            "iouv_outbox_oldest_age_seconds",
            "How long the oldest message owed to an agent has waited (0: none).",
        )
        oldest = owed["oldest"]
        age.add_metric([], (timezone.now() - oldest).total_seconds() if oldest else 0.0)
        yield age

        yield from self._celery()

    def _celery(self) -> Iterator[Any]:
        queue = GaugeMetricFamily(
            "iouv_celery_queue_length", "Tasks waiting for a worker.", labels=["queue"]
        )
        try:
            for name, length in _celery_queue_lengths().items():
                queue.add_metric([name], length)
        except Exception as exc:  # the broker away: the series is missing, which alerts
            log.warning("metrics: the broker's queues could not be read: %s", exc)
        yield queue
        failures = CounterMetricFamily(
            "iouv_celery_task_failures", "Celery tasks that raised.", labels=["task"]
        )
        names = _celery_task_names()
        try:
            counted = cache.get_many([_FAILURES_KEY.format(name) for name in names])
        except Exception as exc:
            log.warning("metrics: the task failures could not be read: %s", exc)
            counted = {}
        for name in names:
            failures.add_metric([name], counted.get(_FAILURES_KEY.format(name), 0))
        yield failures


_collector = PlatformCollector()


def _registry() -> CollectorRegistry:
    """What one scrape reads: the platform's gauges, and the counters of this process
    (or, in multiprocess mode, of every process on the machine)."""
    registry = CollectorRegistry()
    if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        multiprocess.MultiProcessCollector(registry)  # type: ignore[no-untyped-call]
    else:
        registry.register(RELAY_ACKS)
        registry.register(RELAY_ROUND_TRIP)
    registry.register(_collector)
    return registry


def _allowed(request: HttpRequest) -> bool:
    token: str = settings.IOUV_METRICS_TOKEN
    if token:
        scheme, _, given = request.headers.get("Authorization", "").partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(given.strip(), token)
    address = client_address(request)
    return address is not None and ipaddress.ip_address(address).is_loopback


def metrics(request: HttpRequest) -> HttpResponse:
    """Prometheus' text format; 404 for a client not allowed (module docstring)."""
    if not _allowed(request):
        raise Http404("no such page")
    started = time.monotonic()
    body = generate_latest(_registry())
    log.debug("metrics collected in %.3f s", time.monotonic() - started)
    return HttpResponse(body, content_type=CONTENT_TYPE_LATEST)
