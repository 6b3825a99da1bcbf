"""Spectating: the sessions there are to watch, and watching one."""

from __future__ import annotations

from django.contrib import messages
from django.contrib.auth.decorators import login_required
from django.db.models import QuerySet
from django.http import Http404, HttpResponse
from django.shortcuts import get_object_or_404, redirect, render
from django.views.decorators.cache import never_cache

from accounts.users import AuthenticatedHttpRequest
from kinds.spectate.kind import Spectate
from services.kit import (
    FINAL,
    DeploymentError,
    grant_issue,
    log_lines,
    session_situation,
    session_summary,
    session_vehicle_names,
    throttled,
    user_can_use,
    user_task_json,
)
from services.models import Service, Session


def sessions_spectatable() -> QuerySet[Session]:
    """Live sessions whose main vehicle streams video: what spectators may watch."""
    return (
        Session.objects.exclude(state__in=FINAL)
        .filter(
            state__in=[Session.State.ASSIGNED, Session.State.ACTIVE],
            assignments__active=True,
            assignments__vehicle__profile__video=True,
        )
        .select_related("service", "user")
        .distinct()
        .order_by("-created_at")
    )


def _spectate_service(request: AuthenticatedHttpRequest) -> Service:
    service = Service.objects.filter(kind=Spectate.name, is_active=True).first()
    if service is None or not user_can_use(request.user, service):
        raise Http404("spectating is not open to you")
    return service


@login_required
def spectate(request: AuthenticatedHttpRequest) -> HttpResponse:
    """Vehicles streaming video in a live session, to watch."""
    _spectate_service(request)
    sessions = [(s, session_situation(s)) for s in sessions_spectatable()]
    return render(request, "spectate/list.html", {"sessions": sessions})


@never_cache  # the page carries a signed grant: no cache may keep it
@login_required
@throttled("grant")  # every view of the page mints a grant
def spectate_session(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """Watch one session's vehicle: video and telemetry, view-only."""
    service = _spectate_service(request)
    session = get_object_or_404(sessions_spectatable(), pk=session_id)
    try:
        task = grant_issue(session=session, user=request.user, role="viewer", allowed_by=service)
    except DeploymentError as exc:
        messages.error(request, str(exc))
        return redirect("spectate")
    return render(
        request,
        "services/controller.html",
        {
            "session": session,
            "summary": session_summary(session),
            "session_vehicles": session_vehicle_names(session),
            "user_task": user_task_json(task, request=request),
            "events": log_lines(session),
            "watching": True,
        },
    )
