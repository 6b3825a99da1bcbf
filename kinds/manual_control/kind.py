"""Manual control, as a service kind: the user drives one vehicle live."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from django import forms

from accounts.users import User
from kinds.manual_control.forms import SessionRequestForm
from services.kit import DemoService, Opened, Request, ServiceKind, session_open
from services.models import Service


class ManualControl(ServiceKind):
    """The platform reserves the best vehicle near the target and deploys its task;
    the user drives it point-to-point from the controller page while the platform
    supervises. The paper's first kind of service."""

    name = "manual_control"
    label = "Manual control"
    user_drives = True
    accepts = frozenset({"target", "relay", "preferences"})
    form_class = SessionRequestForm
    request_template = "manual_control/request.html"

    def request_from_form(self, form: forms.Form) -> Request:
        assert isinstance(form, SessionRequestForm)
        return Request(
            target=form.target(),
            relay=bool(form.cleaned_data["relay"]),
            preferences=form.preferences(),
        )

    def open(self, *, service: Service, user: User, request: Request) -> Opened:
        # Reserved and deployed in one transaction. Only services.sessions.request calls open(),
        # after checking the user's grant.
        return session_open(
            user=user,
            service=service,
            target=request.target,
            params=dict(request.params),
            relay=request.relay,
            preferences=dict(request.preferences),
            deploy=True,
            grant_checked=True,
        )

    def params_clean(self, params: Any) -> dict[str, Any]:
        # Free-form, kept with the session (the API limits their depth and size).
        return dict(params)

    def demo_services(self) -> Mapping[str, DemoService]:
        # Imported here: only the seed reads the demo world's vocabularies.
        from kinds.manual_control.demo import demo_services

        return demo_services()
