"""Matching vehicles to a service's roles, and reserving them atomically.

For each role, the online idle vehicles go through the role's requirements in a fixed
order; the first requirement that leaves no vehicle is the one named in the refusal.
The survivors are ranked (nearest, or first to arrive, then fullest battery) and the
best is reserved with a conditional UPDATE ... WHERE status = 'idle': of two requests
racing for one vehicle, the database lets exactly one update succeed, and a partial
unique index on active assignments backs that up. No table lock is held, so requests
for different vehicles do not wait on each other.

Which requests need a vehicle's position: those with a target. Their ranking, time to
arrive and range (there, the work, and back to its station) are measured from where
the vehicle is, as its agent reports it; a vehicle reporting none (a drone before its
GPS fix, a car that cannot tell) is not matched for them, rather than measured from its
station as if it stood there. A request without a target measures nothing from the
vehicle (the work alone must fit its range) and may be given such a vehicle.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from django.contrib.auth import get_user_model
from django.db import IntegrityError, transaction

from accounts.users import User
from agents.geo import distance_m
from fleet.attributes import DeclaredAttributes
from fleet.feed import fleet_notify
from fleet.models import Vehicle
from fleet.status import vehicles_online
from services.eventlog import event_append
from services.grants import user_can_use
from services.models import Assignment, Service, ServiceRole, Session
from services.sessions import FINAL, session_transition

#: States of a session that holds (or is about to hold) vehicles.
LIVE_STATES = [state for state in Session.State.values if state not in FINAL]


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


def _requirements(role: ServiceRole) -> list[tuple[str, Callable[[Facts], bool]]]:
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


def role_match(
    *,
    role: ServiceRole,
    target: tuple[float, float] | None = None,
    extra_distance_m: float = 0.0,
    exclude: Iterable[Any] = (),
    now: datetime | None = None,
) -> Match:
    """Rank the vehicles that can fill ``role`` now; nothing is written.

    ``extra_distance_m`` is work done at the target (a search pattern, say) that must
    fit in the vehicle's range too. With a ``target``, only vehicles reporting their
    position are ranked (see the module docstring). On no match, ``unmet`` names the
    requirement.
    """
    pool = [
        Facts.from_row(row)
        for row in vehicles_online(now)
        .filter(status=Vehicle.Status.IDLE)
        .exclude(pk__in=list(exclude))
        .values_list(*Facts.FIELDS)
    ]
    if not pool:
        return Match(role, unmet="no vehicle is online and idle")
    for description, test in _requirements(role):
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


def _reserve_first(*, session: Session, match: Match) -> tuple[Assignment, Facts] | None:
    """Reserve the best candidate still free; None when every one was taken meanwhile."""
    for candidate in match.candidates:
        vehicle = candidate.vehicle
        try:
            # One savepoint for both writes: if the insert fails, the status goes back too.
            with transaction.atomic():
                taken = Vehicle.objects.filter(
                    pk=vehicle.pk, status=Vehicle.Status.IDLE, maintenance=False
                ).update(status=Vehicle.Status.RESERVED)
                if not taken:
                    continue  # another request got it first
                assignment = Assignment.objects.create(
                    session=session,
                    role=match.role.name,
                    vehicle_id=vehicle.pk,
                    distance_m=round(candidate.distance_m, 1),
                )
        except IntegrityError:
            continue  # held by another session's active assignment
        fleet_notify([vehicle.pk])
        return assignment, vehicle
    return None


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
    match = role_match(role=role, target=target, extra_distance_m=extra_distance_m, exclude=exclude)
    if match.unmet:
        raise AssignmentError(f"{role.name}: {match.unmet}", session=session, role=role.name)
    with transaction.atomic():
        reserved = _reserve_first(session=session, match=match)
    if reserved is None:
        raise AssignmentError(
            f"{role.name}: every matching vehicle was just taken by other requests",
            session=session,
            role=role.name,
        )
    assignment, vehicle = reserved
    event_append(
        session=session,
        kind="assigned",
        data={
            "role": role.name,
            "vehicle": str(assignment.vehicle_id),
            "vehicle_name": vehicle.name,
            "distance_m": assignment.distance_m,
        },
    )
    return assignment


def role_tightened(role: ServiceRole, preferences: dict[str, Any]) -> ServiceRole:
    """An unsaved copy of ``role`` with the user's wishes added: extra ``cameras`` and
    a higher ``min_battery``. Preferences only ever narrow a service's requirements."""
    tight = copy.copy(role)
    tight.cameras = sorted(set(role.cameras) | set(preferences.get("cameras", [])))
    tight.min_battery = max(role.min_battery, float(preferences.get("min_battery") or 0))
    return tight


def session_open(
    *,
    user: User,
    service: Service,
    target: tuple[float, float] | None = None,
    params: dict[str, Any] | None = None,
    relay: bool = False,
    preferences: dict[str, Any] | None = None,
) -> Session:
    """Record a new session of ``service`` for ``user`` (state ``requested``, logged),
    if the user may use the service and holds fewer than ``max_sessions_per_user``
    live sessions of it. Call it in a transaction with the work that follows.

    Raises AssignmentError (nothing recorded) when the user may not use the service,
    or when over the cap (``over_cap``).
    """
    if not service.is_active or not user_can_use(user, service):
        raise AssignmentError(f"you may not use the service {service.name!r}")
    with transaction.atomic():
        # The user's row is the lock: two requests of one user are counted one after
        # the other, so together they cannot pass the cap.
        get_user_model().objects.select_for_update().filter(pk=user.pk).first()
        live = Session.objects.filter(user=user, service=service, state__in=LIVE_STATES).count()
        cap = service.max_sessions_per_user
        if live >= cap:
            raise AssignmentError(
                f"you already have {live} live session{'s' if live != 1 else ''} of "
                f"{service.name!r} (at most {cap}); end one first",
                over_cap=True,
            )
        session = Session.objects.create(
            service=service,
            user=user,
            target_lat=target[0] if target else None,
            target_lon=target[1] if target else None,
            params=params or {},
            relay=relay,
        )
        event_append(
            session=session,
            kind="requested",
            data={
                "user": user.get_username(),
                "target": list(target) if target else None,
                "relay": relay,
                "preferences": preferences or {},
            },
        )
    return session


def session_request(
    *,
    user: User,
    service: Service,
    target: tuple[float, float] | None = None,
    params: dict[str, Any] | None = None,
    relay: bool = False,
    preferences: dict[str, Any] | None = None,
) -> Session:
    """Open a session of ``service`` for ``user`` and reserve its required roles.

    ``preferences`` (cameras, min_battery) tighten the requirements of every role.

    Returns the session in state ``assigned``. Raises AssignmentError when the user
    has no grant or already holds ``service.max_sessions_per_user`` live sessions of
    it (no session is recorded; ``over_cap`` says which), or a role cannot be filled
    (the session is recorded as failed with the reason, and no vehicle stays reserved).
    """
    session = session_open(
        user=user,
        service=service,
        target=target,
        params=params,
        relay=relay,
        preferences=preferences,
    )
    try:
        # All roles or none: a failure on the second role frees the first.
        with transaction.atomic():
            taken: list[Any] = []
            for role in service.roles.filter(required=True):
                if preferences:
                    role = role_tightened(role, preferences)
                assignment = role_assign(session=session, role=role, target=target, exclude=taken)
                taken.append(assignment.vehicle_id)
    except AssignmentError as exc:
        session_transition(session=session, to=Session.State.FAILED, reason=str(exc))
        raise AssignmentError(str(exc), session=session, role=exc.role) from None
    return session_transition(
        session=session, to=Session.State.ASSIGNED, reason="vehicles reserved"
    )
