"""Whether a request can ever be served, and why one that can is waiting.

Matching (services.sessions.matching) asks who can serve a role *now*: online, idle, charged
enough, in range from where it is. A request none of them can take now may still be
one the fleet serves once a vehicle is back, free or recharged, or one it never can:
no vehicle of its kind, or a trip longer than any capable vehicle flies on a full
battery from its station and back. This module tells the two apart, from the whole
fleet as it is declared (types, attributes, stations), whatever each vehicle is doing:

* :func:`role_capable`: the vehicles that meet a role's requirements (kinds, adapters,
  environments, cameras, features, minimums; a full battery meets any minimum), each
  with what it flies on a full battery (:class:`Reach`); or the first requirement no
  vehicle of the fleet meets;
* :func:`reach_map`: those vehicles' stations and how far each reaches, for the map a
  request is made on;
* :func:`waiting_words`: why a request that can be served waits (the vehicles that
  can take it are busy, offline or charging), with its place in the queue.

A kind refuses what can never be served before it records anything, naming what
would work (services.kinds.RequestError); the rest is accepted and waits.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from agents.geo import distance_m
from fleet.models import Station, Vehicle
from services.kinds import ServiceKind
from services.models import Assignment, Service, ServiceRole, Session
from services.sessions.matching import Facts, role_requirements
from services.sessions.states import FINAL

#: A full battery: what feasibility assumes of every vehicle.
FULL = 100.0


@dataclass(frozen=True)
class Reach:
    """A vehicle that meets a role's requirements, as it would set out with a full
    battery from its station: ``range_m`` is the longest trip it flies there and back
    (its declared range, or less when its endurance at top speed is shorter)."""

    pk: Any
    name: str
    kind: str
    station: str
    home: tuple[float, float]
    range_m: float
    speed_mps: float
    attributes: dict[str, Any]

    def fits(self, trip_m: float) -> bool:
        """Whether a trip of ``trip_m`` (from its station and back) fits a full battery."""
        return trip_m <= self.range_m

    def radius_m(self, work_m: float = 0.0) -> float:
        """How far from its station it can go, do ``work_m`` there, and come back."""
        return max(0.0, (self.range_m - work_m) / 2)


@dataclass(frozen=True)
class Capable:
    """The fleet's answer for one role: the vehicles that meet its requirements, or
    ``unmet``, the first requirement none of them meets (in the matching's words)."""

    role: ServiceRole
    vehicles: list[Reach]
    unmet: str = ""


def _range_m(attributes: dict[str, Any]) -> tuple[float, float]:
    speed = float(attributes.get("max_speed_mps") or 0.0)
    declared = float(attributes.get("max_range_m") or 0.0)
    endurance_m = float(attributes.get("endurance_min") or 0.0) * 60 * speed
    return (min(declared, endurance_m) if speed > 0 else 0.0), speed


def role_capable(role: ServiceRole, *, exclude: Iterable[Any] = ()) -> Capable:
    """The vehicles of the whole fleet (whatever they are doing now, except those in
    ``exclude``) that meet ``role``'s requirements with a full battery, nearest
    station first (by name for equal ones); see the module docstring."""
    excluded = {str(pk) for pk in exclude}
    rows = (
        Vehicle.objects.exclude(pk__in=list(excluded))
        .select_related("vehicle_type", "station")
        .order_by("station__name", "name")
    )
    fleet = []
    for v in rows:
        home = (v.station.lat, v.station.lon)
        fleet.append(
            (
                Facts(
                    v.pk,
                    v.name,
                    v.vehicle_type.kind,
                    v.vehicle_type.adapter,
                    v.attributes or {},
                    FULL,
                    home,
                    home,
                ),
                v.station.name,
            )
        )
    if not fleet:
        return Capable(role, [], unmet="the fleet has no vehicle")
    pool = fleet
    for description, test in role_requirements(role):
        pool = [(facts, station) for facts, station in pool if test(facts)]
        if not pool:
            return Capable(role, [], unmet=f"no vehicle of the fleet has {description}")
    vehicles = []
    for facts, station in pool:
        range_m, speed = _range_m(facts.attributes)
        vehicles.append(
            Reach(
                facts.pk,
                facts.name,
                facts.kind,
                station,
                facts.home,
                range_m,
                speed,
                facts.attributes,
            )
        )
    return Capable(role, vehicles)


def trip_m(reach: Reach, target: tuple[float, float], work_m: float = 0.0) -> float:
    """The trip matching measures for ``reach`` setting out from its station: there,
    the work, and back (services.sessions.matching)."""
    return 2 * distance_m(reach.home, target) + work_m


def km(metres: float) -> str:
    """A distance for people: "850 m", "2.4 km", "12 km"."""
    if metres < 1000:
        return f"{max(10, round(metres, -1)):.0f} m"
    if metres < 10_000:
        return f"{metres / 1000:.1f} km"
    return f"{metres / 1000:.0f} km"


def reach_map(
    vehicles: Sequence[Reach], *, work_m: float = 0.0, words: Any = None
) -> dict[str, Any]:
    """The request map's stations (those of the vehicles that can serve the request,
    the one the map opens on first) and each vehicle's reach: a circle around its
    station as far as it can go, do ``work_m`` there, and come back on a full battery,
    labelled ``words(vehicle, radius_m)`` (default "<name> reaches 3.0 km from
    <station>"). Every station when no vehicle can serve it."""
    stations: dict[str, dict[str, Any]] = {}
    reach = []
    for v in vehicles:
        stations.setdefault(v.station, {"name": v.station, "lat": v.home[0], "lon": v.home[1]})
        radius = v.radius_m(work_m)
        if radius <= 0:
            continue
        text = words(v, radius) if words else f"{v.name} reaches {km(radius)} from {v.station}"
        reach.append(
            {
                "vehicle": v.name,
                "kind": v.kind,
                "station": v.station,
                "lat": v.home[0],
                "lon": v.home[1],
                "radius_m": round(radius),
                "text": text,
            }
        )
    return {"stations": list(stations.values()) or stations_all(), "reach": reach}


def request_map_default(kind: ServiceKind, service: Service) -> dict[str, Any]:
    """The request page's map of a kind that draws none of its own
    (:meth:`ServiceKind.request_map` None): the vehicles of the whole fleet that could
    ever serve the kind's request role, each from its station on a full battery."""
    role = kind.request_role(service)
    if role is None:
        return {"stations": stations_all(), "reach": []}
    return reach_map(role_capable(role).vehicles)


def stations_all() -> list[dict[str, Any]]:
    """Every station, by name (a map with no vehicle to serve it)."""
    return [{"name": s.name, "lat": s.lat, "lon": s.lon} for s in Station.objects.order_by("name")]


# --- waiting -------------------------------------------------------------------------------

_BUSY: dict[str, str] = {
    Vehicle.Status.RESERVED: "busy with another session",
    Vehicle.Status.IN_SERVICE: "busy with another session",
    Vehicle.Status.RELEASING: "finishing another session",
    Vehicle.Status.RETURNING: "flying back to its station",
    Vehicle.Status.FAILSAFE: "busy with another session",
    Vehicle.Status.OFFLINE: "offline",
    Vehicle.Status.MAINTENANCE: "in maintenance",
}


def queue_position(session: Session) -> int:
    """``session``'s place among the live sessions of its service that wait for a
    vehicle (hold none), oldest first: 1 is next."""
    holding = Assignment.objects.filter(active=True).values("session_id")
    earlier = (
        Session.objects.filter(service_id=session.service_id, created_at__lt=session.created_at)
        .exclude(state__in=FINAL)
        .exclude(pk__in=holding)
        .count()
    )
    return earlier + 1


def _ordinal(n: int) -> str:
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def waiting_words(
    *, session: Session, role: ServiceRole, serving: Sequence[tuple[Reach, float]]
) -> str:
    """Why ``session`` waits for a vehicle for ``role`` although the fleet can serve it:
    ``serving`` are the vehicles that can (:func:`role_capable`), each with its trip
    from its station (:func:`trip_m`), which fits a full battery. Says what each of
    them is doing now and the session's place in the queue (:func:`queue_position`).
    Empty when none of them is named (the caller has its own words)."""
    if not serving:
        return ""
    vehicles = Vehicle.objects.in_bulk([reach.pk for reach, _ in serving])
    doing = []
    for reach, trip in serving:
        vehicle = vehicles.get(reach.pk)
        if vehicle is None:
            continue
        battery = vehicle.battery
        needs = min(100.0, 100.0 * trip / reach.range_m) if reach.range_m > 0 else 100.0
        if vehicle.maintenance:
            why = "in maintenance"
        elif vehicle.status != Vehicle.Status.IDLE:
            why = _BUSY.get(vehicle.status, vehicle.get_status_display())
        elif battery is not None and battery < role.min_battery:
            why = f"charging ({battery:.0f} %; the service needs {role.min_battery:.0f} %)"
        elif battery is not None and battery < needs:
            why = f"charging ({battery:.0f} %; this trip needs about {needs:.0f} %)"
        elif vehicle.lat is None or vehicle.lon is None:
            why = "waiting for its position fix"
        else:
            why = "about to be free"
        doing.append(f"{vehicle.name} is {why}")
    if not doing:
        return ""
    place = queue_position(session)
    queue = "next in line" if place == 1 else f"{_ordinal(place)} in line"
    return f"{'; '.join(doing)}: this request is {queue}"
