"""What operators watch (services.supervision.metrics): ``/metrics`` in Prometheus' text format says
how many agents are online, the live sessions by state, the outbox's backlog and its
oldest message's age, the Celery queue and the tasks that failed; only to the machine
itself or to a scraper holding the token."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import pytest
from celery.signals import task_failure
from django.test import Client
from django.utils import timezone
from prometheus_client.parser import text_string_to_metric_families

from fleet.models import AgentMessage, Vehicle
from iouv.celery import app
from services.models import Session
from tests import factories as f
from tests.deployment import alices_session

pytestmark = pytest.mark.django_db


def _scrape(
    client: Client | None = None, **headers: str
) -> dict[tuple[str, tuple[Any, ...]], float]:
    response = (client or Client()).get("/metrics", **headers)
    assert response.status_code == 200, response.status_code
    assert response["Content-Type"].startswith("text/plain")
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(response.content.decode())
        for sample in family.samples
    }


def test_the_fleet_the_sessions_and_the_outbox_as_the_database_has_them() -> None:
    station, vtype = f.station(), f.vehicle_type()
    for _ in range(2):
        f.vehicle(station=station, vtype=vtype)
    f.vehicle(station=station, vtype=vtype, online=False)
    # Assigned, on a vehicle of its own (reserved), its task owed to the agent (the one
    # message owed: it waited 42 s).
    session, vehicle = alices_session()
    Session.objects.create(service=session.service, user=session.user, state="requested")
    AgentMessage.objects.update(created_at=timezone.now() - timedelta(seconds=42))
    AgentMessage.objects.create(
        vehicle=vehicle, kind="revoke", message={}, state=AgentMessage.State.ACKED
    )
    metrics = _scrape()
    assert metrics[("iouv_agents_online", ())] == Vehicle.objects.exclude(status="offline").count()
    assert metrics[("iouv_agents_online", ())] == 3
    assert metrics[("iouv_vehicles", (("status", "offline"),))] == 1
    assert metrics[("iouv_vehicles", (("status", "reserved"),))] == 1
    assert metrics[("iouv_sessions", (("state", "assigned"),))] == 1
    assert metrics[("iouv_sessions", (("state", "requested"),))] == 1
    assert metrics[("iouv_sessions", (("state", "active"),))] == 0
    assert metrics[("iouv_outbox_backlog", ())] == 1
    assert 42 <= metrics[("iouv_outbox_oldest_age_seconds", ())] < 120
    assert metrics[("iouv_celery_queue_length", (("queue", "celery"),))] >= 0


def test_failed_celery_tasks_are_counted_by_task() -> None:
    counted = _scrape()  # every task of the platform is listed, failed or not
    name = "services.expire_grace"
    before = counted[("iouv_celery_task_failures_total", (("task", name),))]
    for _ in range(2):  # as a worker sends it when the task raises
        task_failure.send(sender=app.tasks[name], task_id="t", exception=RuntimeError("boom"))
    after = _scrape()[("iouv_celery_task_failures_total", (("task", name),))]
    assert after == before + 2


def test_only_the_machine_itself_or_the_token_holder_may_read(settings: Any) -> None:
    settings.BEHIND_PROXY = True
    outside = {"HTTP_X_FORWARDED_FOR": "203.0.113.9"}
    assert Client().get("/metrics", **outside).status_code == 404
    settings.IOUV_METRICS_TOKEN = "scrape-secret"
    assert Client().get("/metrics").status_code == 404  # loopback, but no token
    wrong = {"HTTP_AUTHORIZATION": "Bearer nope"}
    assert Client().get("/metrics", **outside, **wrong).status_code == 404
    assert _scrape(**outside, HTTP_AUTHORIZATION="Bearer scrape-secret")
