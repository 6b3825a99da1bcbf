"""Matching vehicles to a service's roles, and reserving them atomically.

For each role, one query reads the online idle vehicles that meet the requirements the
database can check (kind, adapter, numeric minimums, battery, and on PostgreSQL the
cameras, features and environments); the rows read go through all the role's
requirements in a fixed order. When none is left, the whole online idle pool goes
through them again, so that the first requirement that leaves no vehicle is the one
named in the refusal. The survivors are ranked (nearest, or first to arrive, then
fullest battery) and the best is locked (``SELECT ... FOR UPDATE SKIP LOCKED`` of that
one row, still idle and holding no active assignment) and reserved: of two requests
racing for one vehicle, one locks it and the other moves on to its next candidate,
and waits for the row only when no candidate is left (its own agent may have been
writing it); a partial unique index on active assignments backs that up. No table lock
is held, so requests for different vehicles do not wait on each other. A vehicle whose agent has
gone quiet since (fleet.liveness) is left and the next one tried.

Which requests need a vehicle's position: those with a target. Their ranking, time to
arrive and range (there, the work, and back to its station) are measured from where
the vehicle is, as its agent reports it; a vehicle reporting none (a drone before its
GPS fix, a car that cannot tell) is not matched for them, rather than measured from its
station as if it stood there. A request without a target measures nothing from the
vehicle (the work alone must fit its range) and may be given such a vehicle.
"""

from __future__ import annotations

import contextlib
import copy
import math
import operator
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime
from functools import reduce
from typing import Any

from django.db import connection, transaction
from django.db.models import (
    Exists,
    ExpressionWrapper,
    F,
    FloatField,
    OuterRef,
    Q,
    QuerySet,
    Value,
)
from django.utils import timezone

from agents.geo import distance_m
from fleet.attributes import DeclaredAttributes
from fleet.feed import fleet_notify
from fleet.liveness import vehicles_fresh
from fleet.models import Vehicle
from fleet.status import vehicles_online
from services.models import Assignment, Service, ServiceRole, Session
from services.sessions.log import event_append
from services.sessions.states import session_transition_locked


class AssignmentError(Exception):
    """The request cannot be met; ``str(exc)`` names the unmet requirement.

    ``session`` is the failed session recorded for it (None when refused before one
    was created, e.g. for a missing grant).
    """

    def __init__(
        self,
        message: str,
        *,
        session: Session | None = None,
        role: str = "",
        over_cap: bool = False,
    ) -> None:
        super().__init__(message)
        self.session = session
        self.role = role
        #: Refused because the user already holds as many sessions as the service allows.
        self.over_cap = over_cap


@dataclass(frozen=True)
class Facts(DeclaredAttributes):
    """What matching reads of one online idle vehicle.

    Plain values, not model instances: with a thousand vehicles idle, building a
    vehicle, its type and its station for each was most of a request's time.
    """

    pk: Any
    name: str
    kind: str
    adapter: str
    attributes: dict[str, Any]
    battery: float | None
    position: tuple[float, float] | None  # as its agent reports it; None: unknown
    home: tuple[float, float]  # its station

    FIELDS = (
        "pk",
        "name",
        "vehicle_type__kind",
        "vehicle_type__adapter",
        "attributes",
        "battery",
        "lat",
        "lon",
        "station__lat",
        "station__lon",
    )

    @classmethod
    def from_row(cls, row: tuple[Any, ...]) -> Facts:
        pk, name, kind, adapter, attributes, battery, lat, lon, home_lat, home_lon = row
        position = (lat, lon) if lat is not None and lon is not None else None
        return cls(
            pk, name, kind, adapter, attributes or {}, battery, position, (home_lat, home_lon)
        )


@dataclass(frozen=True)
class Candidate:
    """An eligible vehicle and why it ranks where it does."""

    vehicle: Facts
    distance_m: float  # vehicle to target (0 without a target)
    trip_m: float  # vehicle to target, the extra work, and back to its station
    eta_s: float  # distance over top speed

    def rank(self, selection: str) -> tuple[float, float]:
        first = self.eta_s if selection == ServiceRole.Selection.FASTEST else self.distance_m
        return (first, -(self.vehicle.battery or 0.0))


@dataclass
class Match:
    """The outcome of matching one role: ranked candidates, or the requirement that failed."""

    role: ServiceRole
    candidates: list[Candidate] = field(default_factory=list)
    unmet: str = ""


def _attr(vehicle: Facts, name: str) -> Any:
    return vehicle.attributes.get(name)


def _trip(vehicle: Facts, target: tuple[float, float] | None, extra_m: float) -> Candidate:
    """The vehicle's trip to ``target``; with a target, only for a vehicle whose
    position is known (:func:`role_match` filters the others out first)."""
    here, home = vehicle.position, vehicle.home
    if target is not None and here is None:
        raise ValueError(f"{vehicle.name}: no position to measure the trip from")
    out = distance_m(here, target) if target and here else 0.0
    back = distance_m(target, home) if target else 0.0
    trip = out + extra_m + back
    speed = _attr(vehicle, "max_speed_mps") or 0.0
    eta = out / speed if speed > 0 else float("inf")
    return Candidate(vehicle=vehicle, distance_m=out, trip_m=trip, eta_s=eta)


def _range_ok(c: Candidate) -> bool:
    """The trip fits in what the battery has left of the declared range and endurance."""
    v = c.vehicle
    charge = (v.battery if v.battery is not None else 100.0) / 100.0
    if c.trip_m > (_attr(v, "max_range_m") or 0.0) * charge:
        return False
    speed = _attr(v, "max_speed_mps") or 0.0
    if c.trip_m == 0:
        return True
    if speed <= 0:
        return False
    return c.trip_m / speed <= (_attr(v, "endurance_min") or 0.0) * 60 * charge


def _at_least(name: str, minimum: float) -> Callable[[Facts], bool]:
    """A test: the vehicle's attribute ``name`` (0 when not declared) is ``minimum`` or more."""
    return lambda v: (_attr(v, name) or 0.0) >= minimum


def role_requirements(role: ServiceRole) -> list[tuple[str, Callable[[Facts], bool]]]:
    """(description, test) pairs, checked in order; descriptions are user-facing."""
    checks: list[tuple[str, Callable[[Facts], bool]]] = []
    if role.kinds:
        checks.append((f"kind {' or '.join(role.kinds)}", lambda v: v.kind in role.kinds))
    if role.adapters:
        checks.append(
            (
                f"adapter {' or '.join(role.adapters)}",
                lambda v: v.adapter in role.adapters,
            )
        )
    if role.environments:
        checks.append(
            (
                f"operates in {' or '.join(role.environments)}",
                lambda v: bool(set(role.environments) & set(_attr(v, "environments") or [])),
            )
        )
    if role.cameras:
        checks.append(
            (
                f"cameras {' + '.join(role.cameras)}",
                lambda v: set(role.cameras) <= set(v.cameras),
            )
        )
    if role.features:
        checks.append(
            (
                f"features {', '.join(role.features)}",
                lambda v: set(role.features) <= set(v.features),
            )
        )
    for name, minimum in sorted(role.min_attributes.items()):
        checks.append((f"{name} ≥ {minimum:g}", _at_least(name, minimum)))
    checks.append(
        (
            f"battery ≥ {role.min_battery:g}%",
            lambda v: v.battery is not None and v.battery >= role.min_battery,
        )
    )
    return checks


def _capable(role: ServiceRole) -> Q:
    """The role's requirements the database can check, exactly as :func:`role_requirements`
    checks them (it checks them all again on the rows read, so this only narrows)."""
    q = Q(battery__gte=role.min_battery)  # also leaves out vehicles reporting none
    if role.kinds:
        q &= Q(vehicle_type__kind__in=list(role.kinds))
    if role.adapters:
        q &= Q(vehicle_type__adapter__in=list(role.adapters))
    for name, minimum in sorted(role.min_attributes.items()):
        if minimum > 0:  # an undeclared attribute counts as 0, which meets 0
            q &= Q(**{f"attributes__{name}__gte": minimum})
    if connection.features.supports_json_field_contains:  # PostgreSQL; not SQLite
        if role.cameras:
            q &= Q(attributes__cameras__contains=list(role.cameras))
        if role.features:
            q &= Q(attributes__features__contains=list(role.features))
        if role.environments:
            q &= reduce(
                operator.or_,
                (Q(attributes__environments__contains=[env]) for env in role.environments),
            )
    return q


def _pool(
    *,
    narrow: Q | None,
    target: tuple[float, float] | None,
    exclude: list[Any],
    now: datetime | None,
    page: tuple[int, int] | None = None,
) -> list[Facts]:
    """The online idle vehicles (meeting ``narrow``), as plain facts. With ``page``
    (offset, size) and a ``target``: only that slice of them, nearest to the target
    first (by the database, on an equirectangular approximation of the distance)."""
    values = _candidates(narrow=narrow, positioned=target is not None).exclude(pk__in=exclude)
    if page is not None and target is not None:
        lat, lon = target
        values = _nearest_first(values, Value(lat), Value(lon), Value(_east(lat)), page)
    return [Facts.from_row(row) for row in values]


def _east(lat: float) -> float:
    """A degree of longitude, squared, in degrees of latitude at ``lat``."""
    return math.cos(math.radians(lat)) ** 2


def _candidates(*, narrow: Q | None, positioned: bool) -> QuerySet[Vehicle, tuple[Any, ...]]:
    """The online idle vehicles meeting ``narrow``, as :class:`Facts` rows; with
    ``positioned``, only those reporting where they are (module docstring)."""
    rows = vehicles_online().filter(status=Vehicle.Status.IDLE)
    if narrow is not None:
        rows = rows.filter(narrow)
        if positioned:
            rows = rows.filter(lat__isnull=False, lon__isnull=False)
    return rows.values_list(*Facts.FIELDS)


def _nearest_first(
    values: QuerySet[Vehicle, tuple[Any, ...]],
    lat: Any,
    lon: Any,
    east: Any,
    page: tuple[int, int],
) -> QuerySet[Vehicle, tuple[Any, ...]]:
    """``values``' page ``page`` (offset, size), nearest to (``lat``, ``lon``) first (by
    the database, on an equirectangular approximation of the distance)."""
    north_d = F("lat") - lat
    east_d = F("lon") - lon
    offset, size = page
    return values.alias(
        near=ExpressionWrapper(
            north_d * north_d + east_d * east_d * east, output_field=FloatField()
        )
    ).order_by("near", "pk")[offset : offset + size]


def _ranked(
    role: ServiceRole,
    pool: list[Facts],
    target: tuple[float, float] | None,
    extra_distance_m: float,
) -> Match:
    """``pool`` through the role's requirements, in order, then ranked."""
    if not pool:
        return Match(role, unmet="no vehicle is online and idle")
    for description, test in role_requirements(role):
        pool = [v for v in pool if test(v)]
        if not pool:
            return Match(role, unmet=f"no idle vehicle has {description}")
    if target is not None:
        # Distances are measured from where the vehicle is: unknown, nothing to measure.
        pool = [v for v in pool if v.position is not None]
        if not pool:
            return Match(
                role,
                unmet="no idle vehicle reports its position, which the distance to the "
                "target is measured from",
            )
    trips = [_trip(v, target, extra_distance_m) for v in pool]
    reachable = [c for c in trips if _range_ok(c)]
    if not reachable:
        return Match(role, unmet="no idle vehicle can reach the target and return within its range")
    reachable.sort(key=lambda c: c.rank(role.selection))
    return Match(role, candidates=reachable)


def role_match(
    *,
    role: ServiceRole,
    target: tuple[float, float] | None = None,
    extra_distance_m: float = 0.0,
    exclude: Iterable[Any] = (),
    now: datetime | None = None,
) -> Match:
    """Rank the vehicles that can fill ``role`` now; nothing is written. With a target
    and nearest-first selection, the candidates are those of the nearest page of
    vehicles (:data:`POOL_PAGE`) that has any: the best is always among them.

    ``extra_distance_m`` is work done at the target (a search pattern, say) that must
    fit in the vehicle's range too. With a ``target``, only vehicles reporting their
    position are ranked (see the module docstring). On no match, ``unmet`` names the
    requirement.
    """
    excluded = list(exclude)
    if target is not None and role.selection != ServiceRole.Selection.FASTEST:
        # Nearest first: the vehicles nearest the target are read first, a page at a
        # time, until one page yields candidates. With a thousand idle vehicles that is
        # one page, not the whole fleet decoded and measured for every request.
        offset = 0
        while True:
            page = _pool(
                narrow=_capable(role),
                target=target,
                exclude=excluded,
                now=now,
                page=(offset, POOL_PAGE),
            )
            match = _ranked(role, page, target, extra_distance_m)
            if match.candidates:
                return match
            if len(page) < POOL_PAGE:
                break  # none anywhere: the whole pool says why, below
            offset += POOL_PAGE
    match = _ranked(
        role,
        _pool(narrow=_capable(role), target=target, exclude=excluded, now=now),
        target,
        extra_distance_m,
    )
    if match.unmet:
        # Which requirement failed first is told by the whole pool: read it (a refusal
        # only; one read more).
        match = _ranked(
            role,
            _pool(narrow=None, target=target, exclude=excluded, now=now),
            target,
            extra_distance_m,
        )
    return match


#: Vehicles read per page when matching nearest first (see :func:`role_match`). A page's
#: candidates rank before the next page's: a vehicle on a later page is farther.
#: Small, because every row read is decoded (its attributes are JSON) and measured,
#: and the database has already left out the vehicles that cannot serve the role.
POOL_PAGE = 16

#: Why no candidate could be reserved (for the refusal).
TAKEN = "every matching vehicle was just taken by other requests"
QUIET = "no vehicle is online and idle"


#: How long a request waits for a vehicle that is free by its last committed state but
#: whose row another transaction holds: its agent's uplink writing it (a profile, a
#: disconnect) or a competing request reserving it. Either is over in milliseconds; after
#: it the row says whether the vehicle is still free. Bounded, so that nothing a request
#: cannot see keeps it waiting.
LOCKED_WAIT_S = 2.0


def _reserve_first(
    *, session: Session, match: Match, now: datetime | None = None
) -> tuple[Assignment, Facts] | str:
    """Reserve the best candidate still free and heard from; else say why none could
    be: :data:`TAKEN` by other requests, or :data:`QUIET` when every one's agent has
    gone quiet. Call it in a transaction: the chosen vehicle's row stays locked until
    it ends. The assignment's ``vehicle`` is its row as reserved (what its task needs;
    its type and station are read if asked for).

    Candidates whose rows are locked are skipped, not waited for, so that requests
    racing for a fleet spread over it. Only when none could be reserved does the
    request wait (:data:`LOCKED_WAIT_S` at most) for those that were skipped while
    their rows still said free: a vehicle whose own agent was writing its row at that
    moment is reserved, not refused as taken."""
    why = QUIET if match.candidates else TAKEN
    # Its agent not heard from (the sweep has not marked it offline yet): not this one.
    # Lazily, so the best candidate reserved at once costs one freshness read.
    tries: Iterable[Candidate] = (
        c for c in match.candidates if str(c.vehicle.pk) in vehicles_fresh([c.vehicle.pk], now)
    )
    deadline = time.monotonic() + LOCKED_WAIT_S
    pause = 0.005
    while True:
        held: list[Candidate] = []
        for candidate in tries:
            if _reserve(candidate.vehicle.pk):
                assignment = _assigned(session=session, match=match, candidate=candidate)
                return assignment, candidate.vehicle
            why = TAKEN  # another transaction holds it, or got it first
            if _reads_free(candidate.vehicle.pk):
                held.append(candidate)
        if not held or time.monotonic() >= deadline:
            return why
        time.sleep(pause)
        pause = min(2 * pause, 0.1)
        tries = held


def _free(pk: Any) -> QuerySet[Vehicle]:
    """The vehicle ``pk`` if it is idle, in service and holds no active assignment (not
    one found silent and heard from again: the unique index would refuse the
    assignment, and checking here needs no savepoint to go on)."""
    return (
        Vehicle.objects.filter(pk=pk, status=Vehicle.Status.IDLE, maintenance=False)
        .filter(~Exists(Assignment.objects.filter(vehicle_id=OuterRef("pk"), active=True)))
        .order_by()
    )


def _reserve(pk: Any) -> bool:
    """Mark the vehicle ``pk`` reserved if it is free and no other transaction holds its
    row: the row is locked in a subquery that skips a row held elsewhere. The update's
    own condition holds on SQLite too, which has no row locks (its writers take turns)."""
    held_here = _free(pk).select_for_update(skip_locked=True, of=("self",)).values("pk")
    return bool(Vehicle.objects.filter(pk__in=held_here).update(status=Vehicle.Status.RESERVED))


def _reads_free(pk: Any) -> bool:
    """Whether the vehicle ``pk`` is free by its last committed state: when
    :func:`_reserve` failed, its row is held by a transaction not yet over."""
    return _free(pk).exists()


def _assigned(*, session: Session, match: Match, candidate: Candidate) -> Assignment:
    """The assignment of the vehicle just reserved for ``candidate``."""
    vehicle = Vehicle.objects.get(pk=candidate.vehicle.pk)  # its row as reserved, locked
    assignment = Assignment.objects.create(
        session=session,
        role=match.role.name,
        vehicle=vehicle,
        distance_m=round(candidate.distance_m, 1),
    )
    fleet_notify([vehicle.pk])
    return assignment


def _role_reserve(
    *,
    session: Session,
    role: ServiceRole,
    target: tuple[float, float] | None,
    extra_distance_m: float = 0.0,
    exclude: Iterable[Any] = (),
) -> tuple[Assignment, dict[str, Any]]:
    """Reserve the best vehicle for ``role`` (in the caller's transaction); returns the
    assignment and the ``assigned`` event's data, for the caller to log. Raises
    AssignmentError as :func:`role_assign`."""
    now = timezone.now()
    match = role_match(
        role=role, target=target, extra_distance_m=extra_distance_m, exclude=exclude, now=now
    )
    if match.unmet:
        raise AssignmentError(f"{role.name}: {match.unmet}", session=session, role=role.name)
    reserved = _reserve_first(session=session, match=match, now=now)
    if isinstance(reserved, str):
        raise AssignmentError(f"{role.name}: {reserved}", session=session, role=role.name)
    assignment, vehicle = reserved
    return assignment, {
        "role": role.name,
        "vehicle": str(assignment.vehicle_id),
        "vehicle_name": vehicle.name,
        "distance_m": assignment.distance_m,
    }


def role_assign(
    *,
    session: Session,
    role: ServiceRole,
    target: tuple[float, float] | None = None,
    extra_distance_m: float = 0.0,
    exclude: Iterable[Any] = (),
) -> Assignment:
    """Reserve the best vehicle for ``role`` in ``session``.

    Raises AssignmentError naming the unmet requirement, or saying that every matching
    vehicle was just taken.
    """
    # No savepoint: a refusal is raised before anything is written.
    with transaction.atomic(savepoint=False):
        assignment, data = _role_reserve(
            session=session,
            role=role,
            target=target,
            extra_distance_m=extra_distance_m,
            exclude=exclude,
        )
        event_append(session=session, kind="assigned", data=data)
    return assignment


def role_tightened(role: ServiceRole, preferences: dict[str, Any]) -> ServiceRole:
    """An unsaved copy of ``role`` with the user's wishes added: extra ``cameras`` and
    ``features`` (a car's camera arm) and a higher ``min_battery``. Preferences only
    ever narrow a service's requirements."""
    tight = copy.copy(role)
    tight.cameras = sorted(set(role.cameras) | set(preferences.get("cameras", [])))
    tight.features = sorted(set(role.features) | set(preferences.get("features", [])))
    tight.min_battery = max(role.min_battery, float(preferences.get("min_battery") or 0))
    return tight


def session_roles_assign(
    *,
    session: Session,
    service: Service,
    target: tuple[float, float] | None = None,
    preferences: dict[str, Any] | None = None,
) -> list[Assignment]:
    """Reserve ``service``'s required roles for ``session`` (just recorded, in the
    caller's transaction) and move it to ``assigned``: all roles or none.

    ``preferences`` (cameras, min_battery) tighten the requirements of every role.
    When a role cannot be filled, the session fails with the reason (logged; no
    vehicle stays reserved) and AssignmentError is raised: the caller catches it and
    commits the failure. Returns the assignments, with their vehicles read.
    """
    roles = list(ServiceRole.objects.filter(service=service, required=True))
    reserved: list[tuple[Assignment, dict[str, Any]]] = []
    # All roles or none. With one role nothing is written before a refusal; with more,
    # a savepoint takes back the vehicles reserved for the roles before the one failing.
    undo = transaction.atomic() if len(roles) > 1 else contextlib.nullcontext()
    try:
        with undo:
            taken: list[Any] = []
            for role in roles:
                if preferences:
                    role = role_tightened(role, preferences)
                assignment, data = _role_reserve(
                    session=session, role=role, target=target, exclude=taken
                )
                reserved.append((assignment, data))
                taken.append(assignment.vehicle_id)
    except AssignmentError as exc:
        session_transition_locked(session=session, to=Session.State.FAILED, reason=str(exc))
        raise AssignmentError(str(exc), session=session, role=exc.role) from None
    # Logged once every role is filled: a rolled back role leaves no trace in the log.
    for _, data in reserved:
        event_append(session=session, kind="assigned", data=data, locked=True)
    session_transition_locked(
        session=session, to=Session.State.ASSIGNED, reason="vehicles reserved"
    )
    return [assignment for assignment, _ in reserved]
