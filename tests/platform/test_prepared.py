"""iouv.prepared: statements Django composes once and runs with new values.

Each prepared statement must answer exactly as the ORM queryset it was written as:
the same rows, the same model instances (with what select_related joined), the same
conversions (UUIDs, datetimes, JSON) on the database the suite runs on; and it must
refuse what it cannot run the same way instead of running it differently.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import timedelta
from typing import Any

import pytest
from django.db import IntegrityError, connection, transaction
from django.db.models import F, Model, OuterRef, Subquery, signals
from django.db.transaction import TransactionManagementError
from django.test.utils import CaptureQueriesContext
from django.utils import timezone

from fleet.models import AgentMessage, Station, Vehicle
from iouv.prepared import (
    Param,
    PreparedFamily,
    PreparedInsert,
    PreparedQuery,
    PreparedUpdate,
    params_in,
    values_in,
    writes_batched,
)
from tests import factories as f

pytestmark = pytest.mark.django_db

BY_NAME = PreparedQuery(
    lambda: (
        Vehicle.objects.filter(name=Param("name", Vehicle.name))
        .select_related("station", "vehicle_type")
        .order_by("pk")[:1]
    )
)
BY_STATION_AND_STATUS = PreparedQuery(
    lambda: Vehicle.objects.filter(
        station_id=Param("station", Vehicle.station), status=Param("status", Vehicle.status)
    ).order_by("name")
)
NAMES_SEEN_SINCE = PreparedQuery(
    lambda: (
        Vehicle.objects.filter(last_seen__gte=Param("since", Vehicle.last_seen))
        .order_by("name")
        .values_list("name", flat=True)
    )
)
ID_AND_PROFILE = PreparedQuery(
    lambda: Vehicle.objects.filter(pk=Param("vehicle", Vehicle.id)).values_list("id", "profile")
)
MESSAGES_OF = PreparedQuery(
    lambda: AgentMessage.objects.filter(vehicle_id=Param("vehicle", AgentMessage.vehicle)).order_by(
        "id"
    )
)
LOCKED = PreparedQuery(
    lambda: Vehicle.objects.select_for_update().filter(pk=Param("vehicle", Vehicle.id))
)
STATUS_SET = PreparedUpdate(
    lambda: (
        Vehicle.objects.filter(pk=Param("vehicle", Vehicle.id), maintenance=False),
        {"status": Param("status", Vehicle.status), "battery": F("battery") - 1},
    )
)


@pytest.fixture
def fleet() -> list[Vehicle]:
    station = f.station()
    vtype = f.vehicle_type()
    now = timezone.now()
    out = []
    for i, status in enumerate(["idle", "idle", "offline"]):
        v = f.vehicle(station=station, vtype=vtype, name=f"car-{i}")
        Vehicle.objects.filter(pk=v.pk).update(
            status=status, last_seen=now - timedelta(minutes=i), battery=50, profile={"i": i}
        )
        v.refresh_from_db()
        out.append(v)
    return out


def _same(a: Vehicle, b: Vehicle) -> None:
    assert type(a) is type(b)
    for field in Vehicle._meta.concrete_fields:
        assert getattr(a, field.attname) == getattr(b, field.attname), field.name


def test_models_come_back_as_the_orm_reads_them_with_their_joins(fleet):
    for vehicle in fleet:
        got = BY_NAME.first(name=vehicle.name)
        orm = (
            Vehicle.objects.filter(name=vehicle.name)
            .select_related("station", "vehicle_type")
            .order_by("pk")
            .first()
        )
        _same(got, orm)
        # What select_related joined is read with the row: no query to reach it.
        with CaptureQueriesContext(connection) as captured:
            assert got.station.name == orm.station.name
            assert got.vehicle_type.kind == orm.vehicle_type.kind
        assert len(captured) == 0
        assert got._state.adding is False and got._state.db == "default"
    assert BY_NAME.first(name="no such car") is None


def test_every_value_binds_anew_and_the_rows_match_the_orm(fleet):
    station = fleet[0].station_id
    for status in ("idle", "offline", "in_service"):
        got = BY_STATION_AND_STATUS.all(station=station, status=status)
        orm = list(Vehicle.objects.filter(station_id=station, status=status).order_by("name"))
        assert [v.pk for v in got] == [v.pk for v in orm]
    # An id given as text binds as the field binds it.
    assert [v.pk for v in BY_STATION_AND_STATUS.all(station=str(station), status="idle")] == [
        fleet[0].pk,
        fleet[1].pk,
    ]


def test_values_lists_convert_as_the_orm_converts(fleet):
    since = fleet[1].last_seen
    assert NAMES_SEEN_SINCE.all(since=since) == list(
        Vehicle.objects.filter(last_seen__gte=since).order_by("name").values_list("name", flat=True)
    )
    assert NAMES_SEEN_SINCE.all(since=since) == ["car-0", "car-1"]
    vehicle = fleet[2]
    for key in (vehicle.pk, str(vehicle.pk)):
        row = ID_AND_PROFILE.first(vehicle=key)
        assert row == (vehicle.pk, {"i": 2})
        assert isinstance(row[0], uuid.UUID)  # converted, as values_list converts


def test_a_model_query_reads_its_annotations(fleet):
    statement = PreparedQuery(
        lambda: Vehicle.objects.filter(pk=Param("vehicle", Vehicle.id)).annotate(
            station_name=Subquery(Station.objects.filter(pk=OuterRef("station_id")).values("name")),
            twice=F("battery") * 2,
        )
    )
    (got,) = statement.all(vehicle=fleet[1].pk)
    assert (got.name, got.station_name, got.twice) == ("car-1", fleet[1].station.name, 100)


def test_a_relation_binds_by_the_id_of_its_target(fleet):
    vehicle = fleet[0]
    for text in ("one", "two"):
        AgentMessage.objects.create(vehicle=vehicle, kind="task", message={"text": text})
    got = MESSAGES_OF.all(vehicle=str(vehicle.pk))
    assert [m.message["text"] for m in got] == ["one", "two"]
    assert [m.pk for m in got] == list(
        AgentMessage.objects.filter(vehicle=vehicle).order_by("id").values_list("id", flat=True)
    )
    assert MESSAGES_OF.all(vehicle=fleet[1].pk) == []


def test_an_update_changes_what_it_selects_and_counts_it(fleet):
    idle = fleet[0]
    assert STATUS_SET.run(vehicle=idle.pk, status="reserved") == 1
    idle.refresh_from_db()
    assert (idle.status, idle.battery) == ("reserved", 49)
    Vehicle.objects.filter(pk=fleet[1].pk).update(maintenance=True)
    assert STATUS_SET.run(vehicle=fleet[1].pk, status="reserved") == 0
    assert STATUS_SET.run(vehicle=uuid.uuid4(), status="reserved") == 0
    assert Vehicle.objects.filter(status="reserved").count() == 1


def test_an_update_returns_what_it_left_in_the_rows_it_changed(fleet):
    reserve = PreparedUpdate(
        lambda: (
            Vehicle.objects.filter(pk=Param("vehicle", Vehicle.id), status="idle"),
            {"status": "reserved", "battery": F("battery") - 1},
        ),
        returning=("id", "status", "battery", "profile", "last_seen", "station"),
    )
    with CaptureQueriesContext(connection) as statements:
        ((pk, status, battery, profile, seen, station),) = reserve.run_returning(
            vehicle=fleet[0].pk
        )
    assert len(statements) == 1
    stored = Vehicle.objects.get(pk=fleet[0].pk)
    # Converted as the ORM reads them: a UUID, JSON, an aware datetime, a relation's id.
    assert (pk, status, battery, profile) == (stored.pk, "reserved", 49, {"i": 0})
    assert (seen, station) == (stored.last_seen, stored.station_id)
    # A row the filter no longer selects is not changed and gives nothing back.
    assert reserve.run_returning(vehicle=fleet[0].pk) == []
    assert Vehicle.objects.get(pk=fleet[0].pk).battery == 49
    with pytest.raises(TypeError, match="run_returning"):
        reserve.run(vehicle=fleet[1].pk)
    with pytest.raises(TypeError, match="returns nothing"):
        STATUS_SET.run_returning(vehicle=fleet[1].pk, status="idle")


def test_it_is_composed_once(fleet, monkeypatch):
    statement = PreparedQuery(lambda: Vehicle.objects.filter(name=Param("name", Vehicle.name)))
    composed = []
    compile_ = statement._compile

    def counting(using: str):  # type: ignore[no-untyped-def]
        composed.append(using)
        return compile_(using)

    monkeypatch.setattr(statement, "_compile", counting)
    names = [statement.first(name=v.name).name for v in fleet]
    assert names == [v.name for v in fleet]
    assert composed == ["default"]


@pytest.mark.postgres
@pytest.mark.django_db(transaction=True)
def test_a_locking_read_needs_a_transaction_as_in_the_orm(fleet):
    with pytest.raises(TransactionManagementError):
        LOCKED.all(vehicle=fleet[0].pk)
    with transaction.atomic(), CaptureQueriesContext(connection) as captured:
        assert [v.pk for v in LOCKED.all(vehicle=fleet[0].pk)] == [fleet[0].pk]
    assert "FOR UPDATE" in captured.captured_queries[-1]["sql"]


def test_wrong_values_and_unsupported_statements_are_refused(fleet):
    with pytest.raises(TypeError, match="missing"):
        BY_NAME.first()
    with pytest.raises(TypeError, match="unknown"):
        BY_NAME.first(name="car-0", other=1)
    with pytest.raises(TypeError, match="not a model field"):
        Param("x", "name")
    annotated = PreparedQuery(
        lambda: (
            Vehicle.objects.annotate(twice=F("battery") * 2)
            .filter(name=Param("name", Vehicle.name))
            .values_list("name", "twice")
        )
    )
    with pytest.raises(TypeError, match="annotations"):
        annotated.all(name="car-0")
    named = PreparedQuery(lambda: Vehicle.objects.values_list("name", named=True))
    with pytest.raises(TypeError, match="values_list"):
        named.all()
    dicts = PreparedQuery(lambda: Vehicle.objects.values("name"))
    with pytest.raises(TypeError, match="values_list"):
        dicts.all()
    sliced = PreparedUpdate(lambda: (Vehicle.objects.all()[:1], {"status": "idle"}))
    with pytest.raises(TypeError, match="sliced"):
        sliced.run()


def test_an_insert_writes_what_save_writes_and_reads_the_id_back(fleet):
    insert: PreparedInsert[AgentMessage] = PreparedInsert(AgentMessage)
    heard: list[tuple[str, bool]] = []

    def pre(sender, instance, **kwargs):  # type: ignore[no-untyped-def]
        heard.append(("pre", instance._state.adding))

    def post(sender, instance, created, **kwargs):  # type: ignore[no-untyped-def]
        heard.append(("post", created))

    signals.pre_save.connect(pre, sender=AgentMessage)
    signals.post_save.connect(post, sender=AgentMessage)
    try:
        session = uuid.uuid4()
        ours = insert.save(
            AgentMessage(
                vehicle=fleet[0], session_id=session, kind="task", message={"type": "task"}
            )
        )
        theirs = AgentMessage.objects.create(
            vehicle=fleet[0], session_id=session, kind="task", message={"type": "task"}
        )
    finally:
        signals.pre_save.disconnect(pre, sender=AgentMessage)
        signals.post_save.disconnect(post, sender=AgentMessage)
    assert heard == [("pre", True), ("post", True)] * 2
    # The id the database gave it, its auto_now_add time and its defaults, as save sets.
    assert isinstance(ours.pk, int) and ours.pk == theirs.pk - 1
    assert ours._state.adding is False and ours._state.db == "default"
    stored = AgentMessage.objects.get(pk=ours.pk)
    for field in AgentMessage._meta.concrete_fields:
        if field.name not in ("id", "key", "created_at"):
            assert getattr(stored, field.attname) == getattr(theirs, field.attname), field.name
    assert stored.key == ours.key and stored.created_at == ours.created_at
    assert stored.state == "pending" and stored.result == {}
    # A model whose primary key is set before the insert (a UUID) is written with it.
    vehicles: PreparedInsert[Vehicle] = PreparedInsert(Vehicle)
    new = vehicles.save(
        Vehicle(name="car-new", station=fleet[0].station, vehicle_type=fleet[0].vehicle_type)
    )
    assert Vehicle.objects.get(pk=new.pk).name == "car-new"


def test_an_insert_refuses_what_it_cannot_write_as_save_would(fleet):
    insert: PreparedInsert[AgentMessage] = PreparedInsert(AgentMessage)
    with pytest.raises(TypeError, match="new AgentMessage"):
        insert.save(AgentMessage.objects.create(vehicle=fleet[0], kind="task", message={}))
    with pytest.raises(TypeError, match="new AgentMessage"):
        insert.save(fleet[0])  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="expressions"):
        insert.save(AgentMessage(vehicle=fleet[0], kind="task", message={}, attempts=F("id")))
    # An unsaved relation is refused as save refuses it, before anything is written.
    vehicles: PreparedInsert[Vehicle] = PreparedInsert(Vehicle)
    unsaved = Station(name="nowhere", lat=0, lon=0)
    with pytest.raises(ValueError, match="unsaved related object"):
        vehicles.save(Vehicle(name="ghost", station=unsaved, vehicle_type=fleet[0].vehicle_type))
    assert AgentMessage.objects.count() == 1
    assert not Vehicle.objects.filter(name="ghost").exists()


@contextmanager
def _post_saves(model: type[Model]) -> Iterator[list[Any]]:
    """The pks of the ``model`` instances post_save announces within the block, as it
    announces them."""
    seen: list[Any] = []
    uid = f"post-saves-{uuid.uuid4()}"
    signals.post_save.connect(
        lambda sender, instance, **kw: seen.append(instance.pk),
        sender=model,
        weak=False,
        dispatch_uid=uid,
    )
    try:
        yield seen
    finally:
        signals.post_save.disconnect(sender=model, dispatch_uid=uid)


def test_an_insert_that_skips_conflicts_says_which_row_it_skipped(fleet):
    insert: PreparedInsert[AgentMessage] = PreparedInsert(AgentMessage, skip_conflicts=True)
    with _post_saves(AgentMessage) as created, transaction.atomic():
        first = insert.save_unless_taken(
            AgentMessage(vehicle=fleet[0], kind="task", message={"n": 1})
        )
        assert first is not None and isinstance(first.pk, int)
        # Same unique key: not written, not an error, and the transaction goes on.
        again = AgentMessage(key=first.key, vehicle=fleet[1], kind="task", message={"n": 2})
        assert insert.save_unless_taken(again) is None
        assert again._state.adding is True and again.pk is None
        third = AgentMessage.objects.create(vehicle=fleet[1], kind="task", message={"n": 3})
    assert created == [first.pk, third.pk]  # no post_save for the skipped row
    assert sorted(AgentMessage.objects.values_list("message__n", flat=True)) == [1, 3]
    # The plain save of such an insert, and the skip of a plain one, are refused.
    with pytest.raises(TypeError, match="save_unless_taken"):
        insert.save(AgentMessage(vehicle=fleet[0], kind="task", message={}))
    with pytest.raises(TypeError, match="not prepared to skip"):
        PreparedInsert(AgentMessage).save_unless_taken(
            AgentMessage(vehicle=fleet[0], kind="task", message={})
        )


def test_a_family_prepares_one_statement_per_shape_and_keeps_a_few(fleet):
    built: list[int] = []

    def build(count: int) -> PreparedQuery[Vehicle]:
        built.append(count)
        return PreparedQuery(
            lambda: Vehicle.objects.filter(pk__in=params_in("id", Vehicle.id, count)).order_by(
                "name"
            )
        )

    by_ids: PreparedFamily[PreparedQuery[Vehicle]] = PreparedFamily(build, keep=2)
    ids = [v.pk for v in fleet]
    for chosen in (ids[:1], ids[1:], ids[:1][::-1], [ids[2], uuid.uuid4()]):
        got = by_ids[len(chosen)].all(**values_in("id", chosen))
        assert [v.pk for v in got] == list(
            Vehicle.objects.filter(pk__in=chosen).order_by("name").values_list("pk", flat=True)
        )
    assert built == [1, 2]  # lengths 1 and 2, each prepared once
    by_ids[3]  # a third shape: past keep=2 the family starts afresh
    by_ids[1]
    assert built == [1, 2, 3, 1]


# --- writes held until their block ends (writes_batched) -----------------------------

HELD_MESSAGE: PreparedInsert[AgentMessage] = PreparedInsert(AgentMessage, batched=True)
HELD_VEHICLE: PreparedInsert[Vehicle] = PreparedInsert(Vehicle, batched=True)
HELD_UNLESS_TAKEN: PreparedInsert[AgentMessage] = PreparedInsert(
    AgentMessage, skip_conflicts=True, batched=True
)


def _message(vehicle: Vehicle, n: int, **fields: object) -> AgentMessage:
    return AgentMessage(vehicle=vehicle, kind="task", message={"n": n}, **fields)  # type: ignore[arg-type]


def test_held_writes_are_sent_together_when_the_block_ends(fleet):
    changed: list[int] = []
    station, vtype = fleet[0].station, fleet[0].vehicle_type
    with _post_saves(AgentMessage) as posted, transaction.atomic():
        with CaptureQueriesContext(connection) as inside, writes_batched():
            one = HELD_MESSAGE.save(_message(fleet[0], 1))
            two, three = HELD_MESSAGE.save_all([_message(fleet[1], 2), _message(fleet[1], 3)])
            STATUS_SET.run_later(then=changed.append, vehicle=fleet[0].pk, status="busy")
            car = HELD_VEHICLE.save(Vehicle(name="car-new", station=station, vehicle_type=vtype))
            # Nothing sent yet: no id, no post_save, no row, no answer.
            assert one.pk is None and posted == [] and changed == []
            held = len(inside)
        sent = inside.captured_queries[held:]
    assert held == 0, inside.captured_queries
    # PostgreSQL runs them as one statement; SQLite one by one, in the order made.
    assert len(sent) == (1 if connection.vendor == "postgresql" else 4), sent
    # Each insert's id came back onto its instance, in order, then its post_save.
    assert [one.pk, two.pk, three.pk] == sorted(AgentMessage.objects.values_list("pk", flat=True))
    assert posted == [one.pk, two.pk, three.pk]
    assert [m.message["n"] for m in AgentMessage.objects.order_by("pk")] == [1, 2, 3]
    assert one._state.adding is False and one._state.db == "default"
    assert changed == [1]  # the update's rows, once it ran
    fleet[0].refresh_from_db()
    assert fleet[0].status == "busy" and fleet[0].battery == 49
    assert Vehicle.objects.get(pk=car.pk).name == "car-new"


def test_an_error_in_the_block_drops_what_it_held(fleet):
    with (
        pytest.raises(RuntimeError, match="changed my mind"),
        transaction.atomic(),
        writes_batched(),
    ):
        HELD_MESSAGE.save(_message(fleet[0], 1))
        STATUS_SET.run_later(vehicle=fleet[0].pk, status="busy")
        raise RuntimeError("changed my mind")
    assert not AgentMessage.objects.exists()
    fleet[0].refresh_from_db()
    assert fleet[0].status == "idle"


def test_a_write_inside_a_savepoint_is_not_held(fleet):
    # Rolling back to a savepoint must take the write back: it is sent at once.
    with transaction.atomic(), writes_batched():
        kept = HELD_MESSAGE.save(_message(fleet[0], 1))
        try:
            with transaction.atomic():
                undone = HELD_MESSAGE.save(_message(fleet[0], 2))
                assert undone.pk is not None  # sent already
                raise RuntimeError("undo")
        except RuntimeError:
            pass
        assert kept.pk is None  # still held
    assert [m.message["n"] for m in AgentMessage.objects.all()] == [1]


@pytest.mark.django_db(transaction=True)
def test_writes_are_batched_only_inside_a_transaction(fleet):
    with pytest.raises(TransactionManagementError, match="inside a transaction"), writes_batched():
        pass
    # Outside a block a batched insert and run_later run at once.
    changed: list[int] = []
    message = HELD_MESSAGE.save(_message(fleet[0], 1))
    STATUS_SET.run_later(then=changed.append, vehicle=fleet[1].pk, status="busy")
    assert message.pk is not None and changed == [1]


def test_a_held_insert_that_skips_tells_its_then_and_the_rest_is_written(fleet):
    taken = AgentMessage.objects.create(vehicle=fleet[0], kind="task", message={"n": 0})
    answers: list[AgentMessage | None] = []
    with transaction.atomic(), writes_batched():
        skipped = HELD_UNLESS_TAKEN.save_unless_taken(
            _message(fleet[0], 1, key=taken.key), then=answers.append
        )
        written = HELD_UNLESS_TAKEN.save_unless_taken(_message(fleet[0], 2), then=answers.append)
        STATUS_SET.run_later(vehicle=fleet[0].pk, status="busy")
        assert answers == []
    assert answers == [None, written] and written is not None and written.pk is not None
    assert skipped is not None and skipped._state.adding is True  # never written
    assert sorted(AgentMessage.objects.values_list("message__n", flat=True)) == [0, 2]
    fleet[0].refresh_from_db()
    assert fleet[0].status == "busy"


def test_a_held_write_breaking_a_constraint_raises_when_the_block_ends(fleet):
    taken = AgentMessage.objects.create(vehicle=fleet[0], kind="task", message={"n": 0})
    with pytest.raises(IntegrityError), transaction.atomic(), writes_batched():
        HELD_MESSAGE.save(_message(fleet[1], 1))
        HELD_MESSAGE.save(_message(fleet[1], 2, key=taken.key))
    assert list(AgentMessage.objects.values_list("message__n", flat=True)) == [0]
