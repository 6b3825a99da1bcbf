"""Session state machine and the hash-chained session log."""

from __future__ import annotations

import pytest
from django.core.exceptions import ValidationError

from fleet.models import Vehicle
from services.models import Session, SessionEvent
from services.sessions.log import event_append, session_log_verify
from services.sessions.states import SessionStateError, session_transition
from tests import factories as f
from tests.deployment import session_requested

pytestmark = pytest.mark.django_db


@pytest.fixture
def session():
    f.vehicle(station=f.station(), vtype=f.vehicle_type(), name="v")
    return session_requested(user=f.user(), service=f.service()).session


def test_lifecycle_releases_the_vehicle_with_a_reason(session):
    session_transition(session=session, to=Session.State.ACTIVE, reason="user connected")
    assert Vehicle.objects.get().status == Vehicle.Status.RESERVED
    session_transition(session=session, to=Session.State.ENDED, reason="user ended the session")

    session.refresh_from_db()
    assert session.state == Session.State.ENDED
    assert session.reason == "user ended the session"
    assert session.started_at and session.ended_at
    assert Vehicle.objects.get().status == Vehicle.Status.IDLE
    assert not session.assignments.filter(active=True).exists()
    states = [e.data["to"] for e in session.events.filter(kind="state")]
    assert states == ["assigned", "active", "ended"]


def test_final_states_need_a_reason_and_are_final(session):
    with pytest.raises(SessionStateError, match="without a reason"):
        session_transition(session=session, to=Session.State.ABORTED)
    session_transition(session=session, to=Session.State.ABORTED, reason="monitor stop")
    with pytest.raises(SessionStateError, match="cannot go from aborted to active"):
        session_transition(session=session, to=Session.State.ACTIVE, reason="again")


def test_skipping_a_state_is_refused(session):
    session_transition(session=session, to=Session.State.ENDED, reason="never connected")
    fresh = Session.objects.create(service=session.service, user=session.user)
    with pytest.raises(SessionStateError, match="from requested to active"):
        session_transition(session=fresh, to=Session.State.ACTIVE, reason="x")


def test_untouched_log_verifies(session):
    event_append(session=session, kind="command_refused", data={"name": "up", "why": "ceiling"})
    check = session_log_verify(session=session)
    assert check.ok and check.events == session.events.count() >= 4


def test_altering_a_stored_event_breaks_the_chain(session):
    event_append(session=session, kind="note", data={"speed": 3})
    event_append(session=session, kind="note", data={"speed": 4})
    target = session.events.get(kind="note", data__speed=3)
    # Tampering straight in the database, as an attacker with SQL access would.
    SessionEvent.objects.filter(pk=target.pk).update(data={"speed": 30})

    check = session_log_verify(session=session)
    assert not check.ok
    assert check.bad_seq == target.seq
    assert "hash" in check.problem


def test_removing_an_event_breaks_the_chain(session):
    middle = session.events.order_by("seq")[1]
    SessionEvent.objects.filter(pk=middle.pk)._raw_delete(SessionEvent.objects.db)
    check = session_log_verify(session=session)
    assert not check.ok and check.bad_seq == middle.seq + 1


def test_log_is_append_only_through_the_orm(session):
    event = session.events.first()
    event.kind = "rewritten"
    with pytest.raises(ValidationError, match="append-only"):
        event.save()
    with pytest.raises(ValidationError, match="append-only"):
        event.delete()
