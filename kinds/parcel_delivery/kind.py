"""Parcel delivery, as a service kind: what the core asks of it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from django import forms
from django.conf import settings
from django.http import HttpRequest

from accounts.users import User
from agents.missions.spec import MissionSpec
from fleet.models import VehicleType
from kinds.parcel_delivery.events import PARCEL_EVENTS, delivery_event, delivery_task_accepted
from kinds.parcel_delivery.forms import ParcelRequestForm
from kinds.parcel_delivery.missions import MISSIONS, vehicle_mission
from kinds.parcel_delivery.models import CARRIER, KIND, Delivery
from kinds.parcel_delivery.notifications import tracking_url
from kinds.parcel_delivery.presentation import delivery_json
from kinds.parcel_delivery.request import MIN_TRIP_M, params_clean, parcel_request
from services.kit import (
    DemoService,
    EventHandler,
    Opened,
    Reach,
    Request,
    ServiceKind,
    km,
    reach_map,
    role_capable,
)
from services.models import Assignment, Service, ServiceRole, Session


def _on(name: str) -> EventHandler:
    def handler(assignment: Assignment, data: dict[str, Any]) -> None:
        delivery_event(assignment=assignment, name=name, data=data)

    return handler


class ParcelDelivery(ServiceKind):
    """A user picks a pickup and a drop-off and a weight; the vehicle that can carry it
    and arrives first (a drone, or a boat when both points are on water) collects it,
    brings it, releases it and goes home, while the user and the recipient follow it
    on the map with an ETA. Lost or low mid-way, it hands over to another vehicle."""

    name = KIND
    label = "Parcel delivery"
    user_drives = False
    accepts = frozenset()
    form_class = ParcelRequestForm
    request_template = "parcel_delivery/request.html"
    session_template = "parcel_delivery/session.html"
    urls = "kinds.parcel_delivery.urls"
    event_handlers = {name: _on(name) for name in sorted(PARCEL_EVENTS)}
    missions = MISSIONS

    def params_clean(self, params: Mapping[str, Any]) -> dict[str, Any]:
        return params_clean(params)

    def request_role(self, service: Service) -> ServiceRole | None:
        return service.roles.filter(name=CARRIER).first()

    def request_map(self, service: Service) -> dict[str, Any] | None:
        # Where a parcel can be picked up for the shortest trip: by air (land to land)
        # or, for a boat, on the water.
        def words(carrier: Reach, radius_m: float) -> str:
            how = "on the water" if carrier.kind == VehicleType.Kind.AQUATIC else "by air"
            return f"{how}: pickups within {km(radius_m)} of {carrier.station} ({carrier.name})"

        role = self.request_role(service)
        if role is None:
            return super().request_map(service)
        carriers = role_capable(role).vehicles
        return reach_map(carriers, work_m=2 * MIN_TRIP_M, words=words)

    def request_from_form(self, form: forms.Form) -> Request:
        assert isinstance(form, ParcelRequestForm)
        return Request(params=form.params())

    def open(self, *, service: Service, user: User, request: Request) -> Opened:
        return Opened(session=parcel_request(user=user, service=service, params=request.params))

    def session_context(self, *, request: HttpRequest, session: Session) -> dict[str, Any]:
        delivery = Delivery.objects.filter(pk=session.pk).first()
        if delivery is None:
            return {"delivery": None}
        return {
            "delivery": delivery_json(delivery),
            "tracking_url": tracking_url(delivery),
            "tiles": settings.IOUV_MAP_TILES_URL,
        }

    def situation(self, session: Session) -> str:
        delivery = Delivery.objects.filter(pk=session.pk).first()
        what = delivery.status_text if delivery is not None else ""
        return f"Runs by itself, nobody drives it: {what}." if what else ""

    def session_data(self, session: Session) -> dict[str, Any] | None:
        delivery = Delivery.objects.filter(pk=session.pk).first()
        return delivery_json(delivery) if delivery is not None else None

    def vehicle_mission(self, *, assignment: Assignment) -> MissionSpec | None:
        return vehicle_mission(assignment=assignment)

    def task_accepted(self, *, assignment: Assignment) -> None:
        delivery_task_accepted(assignment=assignment)

    def demo_services(self) -> Mapping[str, DemoService]:
        # Imported here: only the seed reads the demo world.
        from kinds.parcel_delivery.demo import demo_services

        return demo_services()
