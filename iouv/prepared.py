"""Queries Django composes once per process, then runs with new values.

Composing a query is most of what a short ORM statement costs the platform: building
the ``Query`` from ``filter()`` and compiling it to SQL took longer than PostgreSQL
took to answer it (a session's request, end, acks and reports are about forty such
statements, half their CPU time in composing). The statements on those paths are
written once with the ORM, with :class:`Param` where a value goes, and kept here as
their SQL and what Django needs to read their rows back; each run only binds the
values, executes and reads, as the ORM would.

The SQL is still Django's: the same models, the same backend's dialect (SQLite in the
embedded set-up, PostgreSQL in production), rows read into model instances by the
same code (``from_db``, ``select_related``'s populators, the fields' converters). What
is not supported is refused when a statement is prepared, never silently run
differently: values that change the SQL's shape (an ``IN`` list: a
:class:`PreparedFamily` holds one statement per length), updates across tables, extra
selects, and annotations outside model queries.

It reads what Django's compiler works out while composing (the selected columns, the
models they fill, their converters), which Django does not document as an interface:
tests/platform/test_prepared.py compares each kind of statement with the ORM's own
answer, so a Django release that changes those fails there first.

Writes can also wait for each other (:func:`writes_batched`): inside such a block the
inserts and updates that may (:class:`PreparedInsert` made with ``batched=True``,
:meth:`PreparedUpdate.run_later`) are held, and sent when the block ends, all in one
statement on PostgreSQL (``WITH w0 AS (INSERT ...), w1 AS (UPDATE ...) SELECT ...``),
one after the other elsewhere. A session's request and its end each write four or
five rows that nothing in their transaction reads back: one round trip instead of
five.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any, Generic, TypeVar, cast

from django.db import DEFAULT_DB_ALIAS, connections, transaction
from django.db.models import Expression, Field, Model, QuerySet, signals
from django.db.models.constants import OnConflict
from django.db.models.query import (
    FlatValuesListIterable,
    ModelIterable,
    ValuesListIterable,
    get_related_populators,
)
from django.db.models.sql import InsertQuery, UpdateQuery
from django.db.transaction import TransactionManagementError

M = TypeVar("M", bound=Model)


class _Slot:
    """Where a :class:`Param`'s value goes in a compiled statement's parameters."""

    __slots__ = ("field", "name")

    def __init__(self, name: str, field: Field[Any, Any]) -> None:
        self.name = name
        self.field = field

    def __repr__(self) -> str:
        return f"<slot {self.name}>"


class Param(Expression):
    """A named value of a prepared statement, where a filter or an update takes one.

    ``field`` is the model field the value is for (``Vehicle.status.field``, a
    relation's field for its id): the value is made ready for the database as that
    field makes its own, so ids, datetimes and JSON bind as the ORM would bind them.
    """

    def __init__(self, name: str, field: Any) -> None:
        # Accept the model attribute (Vehicle.status) as well as its field.
        field = getattr(field, "field", field)
        if not isinstance(field, Field):
            raise TypeError(f"Param {name!r}: {field!r} is not a model field")
        super().__init__(output_field=field)
        self.name = name

    def as_sql(self, compiler: Any, connection: Any) -> tuple[str, tuple[Any, ...]]:
        return "%s", (_Slot(self.name, self.output_field),)

    def __repr__(self) -> str:
        return f"Param({self.name!r})"


@dataclass(frozen=True)
class _Compiled:
    """One statement as a backend runs it: the SQL, its parameters (fixed values and
    slots) and, for a SELECT, what reads its rows back."""

    sql: str
    params: tuple[Any, ...]
    names: frozenset[str]
    locks: bool  # SELECT ... FOR UPDATE: only inside a transaction
    # For a SELECT, how its rows are read, as Django's compiler and ModelIterable read
    # them (worked out while composing): the columns kept, each column's converters...
    col_count: int = 0
    has_extra_select: bool = False
    converters: tuple[tuple[int, tuple[Any, ...], Any], ...] = ()
    returning: tuple[Any, ...] = ()  # for an UPDATE ... RETURNING, the fields it gives
    values: bool = False  # rows as tuples (values_list), not model instances
    flat: bool = False
    # ...and for model instances, the model's columns, the joined models' populators
    # (select_related) and the annotations' columns.
    model: Any = None
    model_start: int = 0
    model_end: int = 0
    init_list: tuple[str, ...] = ()
    populators: tuple[Any, ...] = ()
    annotations: tuple[tuple[str, int], ...] = ()

    def bind(self, values: Mapping[str, Any], connection: Any) -> list[Any]:
        if set(values) != self.names:
            missing, extra = self.names - set(values), set(values) - self.names
            raise TypeError(
                f"prepared statement takes {sorted(self.names)}; "
                f"missing {sorted(missing)}, unknown {sorted(extra)}"
            )
        return [
            p.field.get_db_prep_value(values[p.name], connection, prepared=False)
            if isinstance(p, _Slot)
            else p
            for p in self.params
        ]


def _column_converters(compiler: Any, columns: Sequence[Any]) -> tuple[Any, ...]:
    """What converts each of ``columns`` as it is read: the backend's and the fields'
    converters (Django's get_converters), kept with the statement; :func:`_converted`
    applies them with the running thread's connection."""
    return tuple(
        (position, tuple(convs), expression)
        for position, (convs, expression) in compiler.get_converters(columns).items()
    )


def _converted(
    converters: Sequence[tuple[int, Sequence[Any], Any]], row: Sequence[Any], connection: Any
) -> list[Any]:
    """``row`` with its values converted, as Django's apply_converters does: each
    column's converters (worked out while composing) with this thread's connection."""
    out = list(row)
    for position, column_converters, expression in converters:
        value = out[position]
        for converter in column_converters:
            value = converter(value, expression, connection)
        out[position] = value
    return out


@dataclass
class _Held:
    """One write held by a :class:`WriteBatch`: its SQL and values as bound, the
    fields whose values it gives back, and what to do once it has run (given how many
    rows it wrote and their returned values)."""

    sql: str
    params: Sequence[Any]
    returning: tuple[Any, ...]
    converters: tuple[tuple[int, tuple[Any, ...], Any], ...]
    done: Callable[[int, list[list[Any]]], object] | None


class WriteBatch:
    """Writes held until their :func:`writes_batched` block ends, then sent together.

    Only writes made at the block's own savepoint depth are held: one made inside a
    savepoint opened in the block runs at once, since rolling back to that savepoint
    would not take back a write that had not been sent yet."""

    def __init__(self, using: str, depth: int) -> None:
        self.using = using
        self.depth = depth
        self._held: list[_Held] = []

    def holds(self, using: str) -> bool:
        """Whether a write to ``using`` made now is held (else it runs at once)."""
        return using == self.using and _savepoint_depth(using) == self.depth

    def hold(self, held: _Held) -> None:
        self._held.append(held)

    def flush(self) -> None:
        """Send what is held: one statement where the backend can run writes in a
        WITH clause, each alone elsewhere; then each write's ``done``, in order. The
        block's end calls it; a block that has to read back what it wrote calls it
        first (the batch goes on holding what comes after)."""
        held, self._held = self._held, []
        if not held:
            return
        connection = connections[self.using]
        # A WITH clause's writes are PostgreSQL's; SQLite runs them one by one.
        if len(held) == 1 or connection.vendor != "postgresql":
            results = [_run_alone(connection, one) for one in held]
        else:
            results = _run_together(connection, held)
        for one, (count, rows) in zip(held, results, strict=True):
            if one.done is not None:
                one.done(count, rows)


def _savepoint_depth(using: str) -> int:
    return sum(1 for sid in connections[using].savepoint_ids if sid)


def _run_alone(connection: Any, held: _Held) -> tuple[int, list[list[Any]]]:
    with (
        transaction.mark_for_rollback_on_error(using=connection.alias),
        connection.cursor() as cursor,
    ):
        cursor.execute(held.sql, held.params)
        if not held.returning:
            return int(cursor.rowcount), []
        rows = cursor.fetchall()
    return len(rows), [_converted(held.converters, row, connection) for row in rows]


def _run_together(connection: Any, held: Sequence[_Held]) -> list[tuple[int, list[list[Any]]]]:
    """The held writes as one PostgreSQL statement: each a data-modifying WITH query,
    and one row that says how many rows each wrote (or the arrays of what they
    returned, in the order written)."""
    quote = connection.ops.quote_name
    queries: list[str] = []
    columns: list[str] = []
    params: list[Any] = []
    for i, one in enumerate(held):
        name = f"iouv_w{i}"
        sql = one.sql if one.returning else f"{one.sql} RETURNING 1"
        queries.append(f"{name} AS ({sql})")
        params.extend(one.params)
        if one.returning:
            columns += [
                f"(SELECT array_agg({name}.{quote(f.column)}) FROM {name})" for f in one.returning
            ]
        else:
            columns.append(f"(SELECT count(*) FROM {name})")
    sql = f"WITH {', '.join(queries)} SELECT {', '.join(columns)}"
    with (
        transaction.mark_for_rollback_on_error(using=connection.alias),
        connection.cursor() as cursor,
    ):
        cursor.execute(sql, params)
        (row,) = cursor.fetchall()
    results: list[tuple[int, list[list[Any]]]] = []
    position = 0
    for one in held:
        if not one.returning:
            results.append((int(row[position]), []))
            position += 1
            continue
        arrays = row[position : position + len(one.returning)]
        position += len(one.returning)
        rows = [list(values) for values in zip(*(a or [] for a in arrays), strict=True)]
        results.append(
            (len(rows), [_converted(one.converters, values, connection) for values in rows])
        )
    return results


_batch: ContextVar[WriteBatch | None] = ContextVar("iouv_write_batch", default=None)


def _open_batch(using: str) -> WriteBatch | None:
    """The open batch that holds a write to ``using`` made now, if any."""
    batch = _batch.get()
    return batch if batch is not None and batch.holds(using) else None


@contextmanager
def writes_batched(using: str = DEFAULT_DB_ALIAS) -> Iterator[WriteBatch]:
    """Within the block, the writes that may wait are held and sent when it ends
    without an error (an error drops them, with the rest of its transaction): the
    inserts of a :class:`PreparedInsert` made with ``batched=True`` and the updates of
    :meth:`PreparedUpdate.run_later`. Call it inside a transaction.

    What the block may not do: read back a row a held write writes (it is not written
    yet), or change one row twice (PostgreSQL runs the held writes as one statement, in
    which a second change of a row does not see the first). A held insert's id, when
    the database sets it, is on its instance once the block has ended; a unique
    constraint a held write breaks raises there. A block inside another's joins it."""
    outer = _batch.get()
    if outer is not None:
        if outer.using != using:
            raise TransactionManagementError("write batches of two databases do not nest")
        yield outer
        return
    if not connections[using].in_atomic_block:
        raise TransactionManagementError("writes are batched inside a transaction")
    batch = WriteBatch(using, _savepoint_depth(using))
    token = _batch.set(batch)
    try:
        yield batch
    finally:
        _batch.reset(token)
    batch.flush()


class _Statement:
    """What :class:`PreparedQuery` and :class:`PreparedUpdate` share: the statement
    composed once per database alias, on first use. What is kept holds no connection:
    each run uses its own thread's."""

    def __init__(self, build: Callable[[], Any]) -> None:
        self._build = build
        self._compiled: dict[str, _Compiled] = {}

    def compiled(self, using: str = DEFAULT_DB_ALIAS) -> _Compiled:
        """The statement as ``using``'s backend runs it (composed now if not yet).
        Two threads composing it at once compose the same thing: no lock."""
        found = self._compiled.get(using)
        if found is None:
            found = self._compiled[using] = self._compile(using)
        return found

    def _compile(self, using: str) -> _Compiled:
        raise NotImplementedError

    @staticmethod
    def _slots(params: Sequence[Any]) -> frozenset[str]:
        return frozenset(p.name for p in params if isinstance(p, _Slot))


class PreparedQuery(_Statement, Generic[M]):
    """A SELECT composed once: ``build`` returns the queryset, with :class:`Param` as
    its values, model instances (``select_related`` and ``select_for_update`` as
    written) or ``values_list`` rows. Slice it (``[:1]``) for a LIMIT; :meth:`first`
    does not add one."""

    def _compile(self, using: str) -> _Compiled:
        queryset = self._build()
        if not isinstance(queryset, QuerySet):
            raise TypeError("a prepared query is built from a QuerySet")
        iterable = queryset._iterable_class
        flat = iterable is FlatValuesListIterable
        if iterable not in (ModelIterable, ValuesListIterable, FlatValuesListIterable):
            raise TypeError(f"prepared queries read models or values_list, not {iterable}")
        query = queryset.query
        if query.extra_select or query.combinator:
            raise TypeError("prepared queries take no extra selects or unions")
        if query.annotation_select and iterable is not ModelIterable:
            # values_list puts annotations in an order of its own: not supported.
            raise TypeError("prepared values_list queries take no annotations")
        compiler = query.get_compiler(using=using)
        sql, params = compiler.as_sql()
        fields = [column[0] for column in compiler.select[: compiler.col_count]]
        composite = getattr(compiler, "has_composite_fields", None)  # Django 5.2 on
        if composite is not None and composite(fields):
            raise TypeError("prepared queries read no composite fields")
        converters = _column_converters(compiler, fields)
        compiled = _Compiled(
            sql=sql,
            params=tuple(params),
            names=self._slots(params),
            locks=bool(query.select_for_update)
            and compiler.connection.features.has_select_for_update,
            col_count=compiler.col_count,
            has_extra_select=compiler.has_extra_select,
            converters=converters,
            values=iterable is not ModelIterable,
            flat=flat,
        )
        if iterable is not ModelIterable:
            return compiled
        klass_info, select = compiler.klass_info, compiler.select
        if klass_info is None:
            raise TypeError("a model query selected no model")
        columns = klass_info["select_fields"]
        start, end = columns[0], columns[-1] + 1
        return dataclasses.replace(
            compiled,
            model=klass_info["model"],
            model_start=start,
            model_end=end,
            init_list=tuple(column[0].target.attname for column in select[start:end]),
            # Django 5.2's signature (the stubs know a later one's).
            populators=tuple(get_related_populators(klass_info, select, using)),  # type: ignore[call-arg]
            annotations=tuple(compiler.annotation_col_map.items()),
        )

    def all(self, *, using: str = DEFAULT_DB_ALIAS, **values: Any) -> list[Any]:
        """Every row: model instances, or tuples (single values when flat)."""
        compiled = self.compiled(using)
        connection = connections[using]
        if compiled.locks and connection.get_autocommit():
            raise TransactionManagementError(
                "select_for_update cannot be used outside of a transaction."
            )
        params = compiled.bind(values, connection)
        with connection.cursor() as cursor:
            cursor.execute(compiled.sql, params)
            rows = cursor.fetchall()
        if not rows:
            return []
        if compiled.has_extra_select:  # ordering columns Django adds past the selected
            rows = [row[: compiled.col_count] for row in rows]
        if compiled.converters:
            rows = [_converted(compiled.converters, row, connection) for row in rows]
        if compiled.values:
            return [row[0] for row in rows] if compiled.flat else [tuple(r) for r in rows]
        return [self._model(compiled, row, using) for row in rows]

    def first(self, *, using: str = DEFAULT_DB_ALIAS, **values: Any) -> Any:
        """The first row, or None."""
        rows = self.all(using=using, **values)
        return rows[0] if rows else None

    @staticmethod
    def _model(compiled: _Compiled, row: Sequence[Any], using: str) -> Any:
        """A row as a model instance, as Django's ModelIterable makes it."""
        columns = row[compiled.model_start : compiled.model_end]
        obj = compiled.model.from_db(using, compiled.init_list, columns)
        for populator in compiled.populators:
            populator.populate(row, obj)
        for name, position in compiled.annotations:
            setattr(obj, name, row[position])
        return obj


class PreparedUpdate(_Statement):
    """An UPDATE composed once: ``build`` returns ``(queryset, {field: value})`` as
    ``queryset.update(**values)`` would take them, with :class:`Param` (or fixed
    values, or expressions such as ``F``) as the values.

    ``returning``: names of the model's fields whose values, as the update leaves them,
    each changed row gives back (``UPDATE ... RETURNING``, :meth:`run_returning`): what
    a read after the update would say, without that read's statement."""

    def __init__(self, build: Callable[[], Any], *, returning: Sequence[str] = ()) -> None:
        super().__init__(build)
        self.returning = tuple(returning)

    def _compile(self, using: str) -> _Compiled:
        queryset, changes = self._build()
        if not isinstance(queryset, QuerySet):
            raise TypeError("a prepared update is built from a QuerySet")
        if queryset.query.is_sliced:
            raise TypeError("cannot update a sliced query")
        query = cast(UpdateQuery, queryset.query.chain(UpdateQuery))
        query.add_update_values(changes)
        query.clear_select_clause()
        if query.get_related_updates():
            raise TypeError("prepared updates change one table")
        compiler = query.get_compiler(using=using)
        if compiler.query.count_active_tables() > 1 and not (
            compiler.connection.features.update_can_self_select
        ):
            raise TypeError("this backend selects the rows of a joined update first")
        sql, params = compiler.as_sql()
        converters: tuple[tuple[int, tuple[Any, ...], Any], ...] = ()
        fields: list[Any] = []
        if self.returning:
            connection = compiler.connection
            if not connection.features.can_return_columns_from_insert:
                raise TypeError("this backend cannot return the rows it changes")
            meta = queryset.model._meta
            fields = [meta.get_field(name) for name in self.returning]
            # The same clause an INSERT's RETURNING takes, on both backends.
            returning_sql, _ = connection.ops.return_insert_columns(fields)
            sql = f"{sql} {returning_sql}"
            converters = _column_converters(
                compiler, [field.get_col(meta.db_table) for field in fields]
            )
        return _Compiled(
            sql=sql,
            params=tuple(params),
            names=self._slots(params),
            locks=False,
            converters=converters,
            returning=tuple(fields),
        )

    def run_returning(
        self, *, using: str = DEFAULT_DB_ALIAS, **values: Any
    ) -> list[tuple[Any, ...]]:
        """Run the update; the ``returning`` fields of each row it changed."""
        if not self.returning:
            raise TypeError("this update returns nothing: give it returning fields")
        _count, rows = _run_alone(connections[using], self._held(using, values, None))
        return [tuple(row) for row in rows]

    def run(self, *, using: str = DEFAULT_DB_ALIAS, **values: Any) -> int:
        """Run the update; how many rows it changed."""
        if self.returning:
            raise TypeError("this update returns its rows: use run_returning")
        count, _rows = _run_alone(connections[using], self._held(using, values, None))
        return count

    def run_later(
        self,
        *,
        then: Callable[[int], None] | None = None,
        using: str = DEFAULT_DB_ALIAS,
        **values: Any,
    ) -> None:
        """:meth:`run`, held by the open :func:`writes_batched` block if there is one,
        else now; ``then`` is given how many rows it changed once it has run."""
        if self.returning:
            raise TypeError("this update returns its rows: use run_returning")

        def done(count: int, _rows: list[list[Any]]) -> None:
            if then is not None:
                then(count)

        held = self._held(using, values, done)
        batch = _open_batch(using)
        if batch is None:
            done(*_run_alone(connections[using], held))
        else:
            batch.hold(held)

    def _held(
        self,
        using: str,
        values: Mapping[str, Any],
        done: Callable[[int, list[list[Any]]], object] | None,
    ) -> _Held:
        """The update with ``values`` bound, as a batch holds it or runs it alone."""
        compiled = self.compiled(using)
        params = compiled.bind(values, connections[using])
        return _Held(compiled.sql, params, compiled.returning, compiled.converters, done)


@dataclass(frozen=True)
class _CompiledInsert:
    sql: str
    fields: tuple[Any, ...]  # the columns written, in order
    returning: tuple[Any, ...]  # the fields the database fills in (an auto id)
    converters: tuple[tuple[int, tuple[Any, ...], Any], ...]


class PreparedInsert(Generic[M]):
    """The INSERT of one new ``model`` instance, composed once: what
    ``obj.save(force_insert=True)`` writes (``Model.objects.create``), with the same
    values (each field's ``pre_save`` and database preparation), the same signals and
    the database's id set on the instance. For plain tables: a model with parents
    (multi-table inheritance), a field with a placeholder of its own or an expression as
    a value is refused.

    ``skip_conflicts``: the row is not written when it would break a unique constraint
    (``ON CONFLICT DO NOTHING``; SQLite's ``INSERT OR IGNORE``), and :meth:`save_unless_taken`
    says so instead of raising, without aborting the transaction it runs in. For models
    whose id the database sets, which is how the insert is told apart from the skip.

    ``batched``: inside a :func:`writes_batched` block the insert is held and sent with
    the block's other writes; its post_save, and the id the database sets, come then."""

    def __init__(
        self, model: type[M], *, skip_conflicts: bool = False, batched: bool = False
    ) -> None:
        self.model = model
        self.skip_conflicts = skip_conflicts
        self.batched = batched
        self._compiled: dict[tuple[str, bool], _CompiledInsert] = {}

    def _fields(self, using: str, pk_set: bool) -> tuple[list[Any], list[Any]]:
        """The columns written and the fields the database fills in, checked."""
        meta = self.model._meta
        if meta.parents:
            raise TypeError("prepared inserts write one table")
        fields = [f for f in meta.local_concrete_fields if not f.generated]
        if not pk_set:
            fields = [f for f in fields if f is not meta.auto_field]
        if any(hasattr(f, "get_placeholder") for f in fields):
            raise TypeError("prepared inserts take fields bound as plain values only")
        returning = list(meta.db_returning_fields) if not pk_set else []
        if returning and not connections[using].features.can_return_columns_from_insert:
            raise TypeError("this backend cannot return the inserted id")
        if self.skip_conflicts and not returning:
            raise TypeError("a skipped insert is told by the id the database returns")
        return fields, returning

    def _compile(self, using: str, pk_set: bool) -> _CompiledInsert:
        fields, returning = self._fields(using, pk_set)
        query = InsertQuery(
            self.model, on_conflict=OnConflict.IGNORE if self.skip_conflicts else None
        )
        query.insert_values(fields, [self.model()], raw=False)
        compiler = query.get_compiler(using=using)
        compiler.returning_fields = returning or None
        ((sql, _params),) = compiler.as_sql()
        table = self.model._meta.db_table
        converters = _column_converters(compiler, [f.get_col(table) for f in returning])
        return _CompiledInsert(sql, tuple(fields), tuple(returning), converters)

    def save(self, obj: M, *, using: str = DEFAULT_DB_ALIAS) -> M:
        """Insert ``obj`` (a new instance of the model) and return it, saved (or held,
        with ``batched``)."""
        if self.skip_conflicts:
            raise TypeError("this insert may skip its row: use save_unless_taken")
        self._insert(obj, using, None)
        return obj

    def save_unless_taken(
        self,
        obj: M,
        *,
        using: str = DEFAULT_DB_ALIAS,
        then: Callable[[M | None], None] | None = None,
    ) -> M | None:
        """Insert ``obj`` unless a stored row already holds one of its unique values:
        ``obj`` saved, else None (``obj`` is left unsaved and no post_save is sent).

        ``then`` is given that answer once the insert has run: with ``batched``, in a
        :func:`writes_batched` block, that is when the block ends, and ``obj`` (held) is
        returned meanwhile."""
        if not self.skip_conflicts:
            raise TypeError("this insert is not prepared to skip conflicts")
        return self._insert(obj, using, then)

    def _prepare(self, obj: M, using: str) -> None:
        """Model.save's checks and pre_save, and the pk set if Python makes it."""
        if type(obj) is not self.model or not obj._state.adding:
            raise TypeError(f"a prepared insert saves new {self.model.__name__} instances")
        # Model.save's own checks of the relations (not in the stubs).
        obj._prepare_related_fields_for_save(operation_name="save")  # type: ignore[attr-defined]
        signals.pre_save.send(
            sender=self.model, instance=obj, raw=False, using=using, update_fields=None
        )
        if obj._get_pk_val() is None:
            pk = self.model._meta.pk.get_pk_value_on_save(obj)
            setattr(obj, self.model._meta.pk.attname, pk)

    def _insert(self, obj: M, using: str, then: Callable[[M | None], None] | None) -> M | None:
        self._prepare(obj, using)
        key = (using, obj._get_pk_val() is not None)
        compiled = self._compiled.get(key)
        if compiled is None:
            compiled = self._compiled[key] = self._compile(*key)
        connection = connections[using]
        params = []
        for field in compiled.fields:
            value = field.pre_save(obj, True)
            if hasattr(value, "resolve_expression"):
                raise TypeError(f"{field.name}: a prepared insert takes values, not expressions")
            params.append(field.get_db_prep_save(value, connection=connection))

        def written(count: int, rows: list[list[Any]]) -> M | None:
            saved: M | None = None
            if rows or not self.skip_conflicts:
                _written(obj, compiled.returning, rows[0] if rows else None, using)
                saved = obj
            if then is not None:
                then(saved)
            return saved

        held = _Held(compiled.sql, params, compiled.returning, compiled.converters, written)
        batch = _open_batch(using) if self.batched else None
        if batch is not None:
            batch.hold(held)
            return obj
        return written(*_run_alone(connection, held))

    def save_all(self, objs: Sequence[M], *, using: str = DEFAULT_DB_ALIAS) -> list[M]:
        """Insert the new instances ``objs`` with one statement, as
        ``bulk_create(objs)`` would, with each one's signals, and return them (held,
        with ``batched``). Composed for each call: its SQL depends on the number of
        rows."""
        if self.skip_conflicts:
            raise TypeError("save_all writes every row: not for an insert that skips")
        objs = list(objs)
        if not objs:
            return objs
        for obj in objs:
            self._prepare(obj, using)
        pk_set = {obj._get_pk_val() is not None for obj in objs}
        if len(pk_set) > 1:
            raise TypeError("save_all takes instances that all have an id, or none")
        fields, returning = self._fields(using, pk_set.pop())
        query = InsertQuery(self.model)
        query.insert_values(fields, list[Model](objs), raw=False)
        compiler = query.get_compiler(using=using)
        compiler.returning_fields = returning or None
        ((sql, params),) = compiler.as_sql()
        table = self.model._meta.db_table
        converters = _column_converters(compiler, [f.get_col(table) for f in returning])

        def written(count: int, rows: list[list[Any]]) -> None:
            returned: Sequence[Any] = rows if returning else [None] * len(objs)
            for obj, row in zip(objs, returned, strict=True):
                _written(obj, returning, row, using)

        held = _Held(sql, params, tuple(returning), converters, written)
        batch = _open_batch(using) if self.batched else None
        if batch is not None:
            batch.hold(held)
        else:
            written(*_run_alone(connections[using], held))
        return objs


def _written(obj: Model, fields: Sequence[Any], row: Sequence[Any] | None, using: str) -> None:
    """``obj`` as Model.save leaves a new instance: the values the database set
    (``fields``, read back as ``row``), saved to ``using``, post_save sent."""
    if row is not None:
        for field, value in zip(fields, row, strict=True):
            setattr(obj, field.attname, value)
    obj._state.adding = False
    obj._state.db = using
    signals.post_save.send(
        sender=type(obj),
        instance=obj,
        created=True,
        update_fields=None,
        raw=False,
        using=using,
    )


S = TypeVar("S")


class PreparedFamily(Generic[S]):
    """Prepared statements whose SQL depends on a shape (an ``IN`` list's length, a
    role's requirements): ``build(shape)`` makes the statement for a shape on its first
    use. At most ``keep`` shapes are kept; past that the family starts afresh, so
    shapes that come and go (services edited at will) cannot grow it without bound."""

    def __init__(self, build: Callable[[Any], S], *, keep: int = 64) -> None:
        self._build = build
        self._keep = keep
        self._statements: dict[Any, S] = {}

    def __getitem__(self, shape: Any) -> S:
        statement = self._statements.get(shape)
        if statement is None:
            if len(self._statements) >= self._keep:
                self._statements.clear()
            statement = self._statements[shape] = self._build(shape)
        return statement


def params_in(name: str, field: Any, count: int) -> list[Any]:
    """``count`` Params (``name0``, ``name1``...) for an ``IN`` list of that length;
    bind them with :func:`values_in`."""
    return [Param(f"{name}{i}", field) for i in range(count)]


def values_in(name: str, values: Sequence[Any]) -> dict[str, Any]:
    """The values of :func:`params_in`'s Params, by name."""
    return {f"{name}{i}": value for i, value in enumerate(values)}
