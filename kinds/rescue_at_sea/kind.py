"""Person rescue at sea, as a service kind: what the core asks of it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from django import forms
from django.conf import settings
from django.http import HttpRequest

from accounts.users import User
from agents.missions.spec import MissionSpec
from kinds.rescue_at_sea.events import MISSION_EVENTS, mission_event, mission_task_accepted
from kinds.rescue_at_sea.forms import RescueRequestForm
from kinds.rescue_at_sea.missions import MISSIONS, vehicle_mission
from kinds.rescue_at_sea.models import KIND, Mission
from kinds.rescue_at_sea.presentation import mission_json
from kinds.rescue_at_sea.request import MAX_ALTITUDE_M, MIN_ALTITUDE_M, rescue_request
from services.kit import DemoService, EventHandler, Opened, Request, RequestError, ServiceKind
from services.models import Assignment, Service, Session


def _on_mission_event(name: str) -> EventHandler:
    def handler(assignment: Assignment, data: dict[str, Any]) -> None:
        mission_event(assignment=assignment, name=name, data=data)

    return handler


class RescueAtSea(ServiceKind):
    """A drone searches the area the user drew, a second vehicle brings a life jacket
    to the person it finds, the rescue team is alerted, everyone returns. The user
    watches (the search drone's thermal video, the live map); the platform runs it."""

    name = KIND
    label = "Person rescue at sea"
    user_drives = False
    accepts = frozenset()
    form_class = RescueRequestForm
    request_template = "rescue_at_sea/request.html"
    session_template = "rescue_at_sea/mission.html"
    urls = "kinds.rescue_at_sea.urls"
    event_handlers = {name: _on_mission_event(name) for name in sorted(MISSION_EVENTS)}
    missions = MISSIONS

    def params_clean(self, params: Mapping[str, Any]) -> dict[str, Any]:
        unknown = sorted(set(params) - {"area", "altitude_m"})
        if unknown:
            raise RequestError("unknown field", field=f"params.{unknown[0]}")
        if "area" not in params:
            raise RequestError(
                "is required: the search area, [[lat, lon], ...]", field="params.area"
            )
        cleaned: dict[str, Any] = {"area": params["area"]}
        altitude = params.get("altitude_m")
        if altitude is not None:
            if isinstance(altitude, bool) or not isinstance(altitude, int | float):
                raise RequestError(
                    f"must be a number from {MIN_ALTITUDE_M:g} to {MAX_ALTITUDE_M:g}",
                    field="params.altitude_m",
                )
            cleaned["altitude_m"] = float(altitude)
        return cleaned

    def request_from_form(self, form: forms.Form) -> Request:
        data = form.cleaned_data
        params: dict[str, Any] = {"area": data["area"]}
        if data.get("altitude_m") is not None:
            params["altitude_m"] = data["altitude_m"]
        return Request(params=params)

    def open(self, *, service: Service, user: User, request: Request) -> Opened:
        session = rescue_request(
            user=user,
            service=service,
            area=request.params["area"],
            altitude_m=request.params.get("altitude_m"),
        )
        return Opened(session=session)

    def session_context(self, *, request: HttpRequest, session: Session) -> dict[str, Any]:
        mission = Mission.objects.filter(pk=session.pk).first()
        return {
            "mission": mission_json(mission) if mission is not None else None,
            "tiles": settings.IOUV_MAP_TILES_URL,
        }

    def situation(self, session: Session) -> str:
        mission = Mission.objects.filter(pk=session.pk).first()
        what = mission.status_text if mission is not None else ""
        return f"Runs by itself, nobody drives it: {what}." if what else ""

    def session_data(self, session: Session) -> dict[str, Any] | None:
        mission = Mission.objects.filter(pk=session.pk).first()
        return mission_json(mission) if mission is not None else None

    def vehicle_mission(self, *, assignment: Assignment) -> MissionSpec | None:
        return vehicle_mission(assignment=assignment)

    def task_accepted(self, *, assignment: Assignment) -> None:
        mission_task_accepted(assignment=assignment)

    def demo_services(self) -> Mapping[str, DemoService]:
        # Imported here: only the seed reads the demo world.
        from kinds.rescue_at_sea.demo import demo_services

        return demo_services()

    def demo_seed(self) -> None:
        from kinds.rescue_at_sea.demo import demo_seed

        demo_seed()
