"""An outbox pass (fleet.outbox._take_due): the pending messages of this process's
vehicles, due now, in order, marked as sent; another vehicle's rows left alone, for one
row as for a backlog (after an outage)."""

from __future__ import annotations

import pytest
from django.utils import timezone

from fleet import outbox
from fleet.models import AgentMessage
from tests import factories as f

pytestmark = pytest.mark.django_db


@pytest.mark.parametrize("count", [1, 40])
def test_a_pass_takes_the_due_rows_of_its_vehicles_in_order_and_marks_them_sent(count):
    station, vtype = f.station(), f.vehicle_type()
    ours, theirs = f.vehicle(station=station, vtype=vtype), f.vehicle(station=station, vtype=vtype)
    for i in range(count):
        AgentMessage.objects.create(vehicle=ours, kind="task", message={"i": i})
    AgentMessage.objects.create(vehicle=theirs, kind="task", message={"i": -1})
    now = timezone.now()

    due = outbox._take_due(vehicle_ids=[str(ours.pk)], fresh=[], now=now)

    assert [row["message"] for row in due] == [{"i": i} for i in range(count)]
    assert [row["id"] for row in due] == sorted(row["id"] for row in due)
    mine = AgentMessage.objects.filter(vehicle=ours)
    assert set(mine.values_list("attempts", "sent_at")) == {(1, now)}
    other = AgentMessage.objects.get(vehicle=theirs)
    assert (other.attempts, other.sent_at) == (0, None)
    # Just sent, not yet due again.
    assert outbox._take_due(vehicle_ids=[str(ours.pk)], fresh=[], now=now) == []
