"""Aerial survey, as a service kind: what the core asks of it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from django import forms
from django.conf import settings
from django.http import HttpRequest

from accounts.users import User
from agents.missions.spec import MissionSpec
from kinds.survey.events import (
    SURVEY_EVENTS,
    survey_event,
    survey_photo_received,
    survey_task_accepted,
)
from kinds.survey.forms import SurveyRequestForm
from kinds.survey.missions import MISSIONS, vehicle_mission
from kinds.survey.models import KIND, SURVEYOR, Survey
from kinds.survey.planning import surveyor_role
from kinds.survey.presentation import survey_json
from kinds.survey.request import params_clean, survey_request
from services.kit import (
    DemoService,
    EventHandler,
    Opened,
    Request,
    ServiceKind,
    reach_map,
    role_capable,
)
from services.models import Assignment, Service, ServiceRole, Session, SessionArtifact


def _on(name: str) -> EventHandler:
    def handler(assignment: Assignment, data: dict[str, Any]) -> None:
        survey_event(assignment=assignment, name=name, data=data)

    return handler


class AerialSurvey(ServiceKind):
    """A user draws an area and picks a ground resolution; a drone with a camera and the
    range photographs it from a grid of lines planned for its camera; the user watches
    the photos cover the area and gets a mosaic to overlay or download. A drone lost or
    low mid-way hands over to another, from the first photo not taken."""

    name = KIND
    label = "Aerial survey"
    user_drives = False
    accepts = frozenset()
    form_class = SurveyRequestForm
    request_template = "survey/request.html"
    session_template = "survey/session.html"
    urls = "kinds.survey.urls"
    event_handlers = {name: _on(name) for name in sorted(SURVEY_EVENTS)}
    missions = MISSIONS

    def params_clean(self, params: Mapping[str, Any]) -> dict[str, Any]:
        return params_clean(params)

    def request_role(self, service: Service) -> ServiceRole | None:
        return service.roles.filter(name=SURVEYOR).first()

    def request_map(self, service: Service) -> dict[str, Any] | None:
        if self.request_role(service) is None:
            return super().request_map(service)
        return reach_map(role_capable(surveyor_role(service)).vehicles)

    def request_from_form(self, form: forms.Form) -> Request:
        assert isinstance(form, SurveyRequestForm)
        return Request(params=form.params())

    def open(self, *, service: Service, user: User, request: Request) -> Opened:
        return Opened(session=survey_request(user=user, service=service, params=request.params))

    def session_context(self, *, request: HttpRequest, session: Session) -> dict[str, Any]:
        survey = Survey.objects.filter(pk=session.pk).first()
        if survey is None:
            return {"survey": None}
        return {"survey": survey_json(survey), "tiles": settings.IOUV_MAP_TILES_URL}

    def situation(self, session: Session) -> str:
        survey = Survey.objects.filter(pk=session.pk).first()
        what = survey.status_text if survey is not None else ""
        return f"Runs by itself, nobody drives it: {what}." if what else ""

    def session_data(self, session: Session) -> dict[str, Any] | None:
        survey = Survey.objects.filter(pk=session.pk).first()
        return survey_json(survey) if survey is not None else None

    def vehicle_mission(self, *, assignment: Assignment) -> MissionSpec | None:
        return vehicle_mission(assignment=assignment)

    def task_accepted(self, *, assignment: Assignment) -> None:
        survey_task_accepted(assignment=assignment)

    def artifact_received(self, *, artifact: SessionArtifact) -> None:
        survey_photo_received(artifact=artifact)

    def demo_services(self) -> Mapping[str, DemoService]:
        # Imported here: only the seed reads the demo world.
        from kinds.survey.demo import demo_services

        return demo_services()
