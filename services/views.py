"""Portal views: thin, they parse, call a service function and render."""

from __future__ import annotations

from typing import Any

from django.conf import settings
from django.contrib import messages
from django.contrib.auth.decorators import login_required, permission_required
from django.db import connection
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import get_object_or_404, redirect, render
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_POST

from accounts.roles import user_roles
from fleet.models import Station
from services.assignment import AssignmentError, session_request
from services.deployment import (
    DeploymentError,
    grant_issue,
    session_deploy,
    session_end,
    session_revoke,
    user_task_json,
)
from services.forms import RescueRequestForm, SessionRequestForm
from services.grants import services_for_user, user_can_use
from services.models import Mission, Service, Session
from services.rescue import RescueError, mission_json, rescue_request
from services.selectors import service_vehicles_matching, session_summary, sessions_spectatable
from services.sessions import FINAL


@login_required
def catalog(request: HttpRequest) -> HttpResponse:
    """The services this user may request, and their own live sessions."""
    services = services_for_user(request.user).prefetch_related("roles")
    mine = (
        Session.objects.filter(user=request.user).exclude(state__in=FINAL).select_related("service")
    )
    return render(
        request,
        "services/catalog.html",
        {"services": services, "roles": sorted(user_roles(request.user)), "live": mine},
    )


@login_required
def service_request(request: HttpRequest, slug: str) -> HttpResponse:
    """The request form of one service; a valid POST reserves, deploys and opens the
    session page (the user task)."""
    service = get_object_or_404(Service, slug=slug, is_active=True)
    if not user_can_use(request.user, service):
        raise Http404("no such service for you")
    if service.workflow == "spectate":
        return redirect("spectate")
    if service.workflow == "rescue_at_sea":
        return _rescue_request(request, service)
    form = SessionRequestForm(request.POST or None)
    if request.method == "POST" and form.is_valid():
        try:
            session = session_request(
                user=request.user,
                service=service,
                target=form.target(),
                relay=form.cleaned_data["relay"],
                preferences=form.preferences(),
            )
            if service.mode == Service.Mode.SYNCHRONOUS:
                session_deploy(session=session)
        except (AssignmentError, DeploymentError) as exc:
            messages.error(request, f"Not possible right now: {exc}")
        else:
            return redirect("session", session_id=session.pk)
    return render(
        request,
        "services/request.html",
        {"service": service, "form": form, "available": service_vehicles_matching(service)},
    )


def _rescue_request(request: HttpRequest, service: Service) -> HttpResponse:
    """The rescue's request page: draw the search area on the map."""
    form = RescueRequestForm(request.POST or None)
    if request.method == "POST" and form.is_valid():
        try:
            session = rescue_request(
                user=request.user,
                service=service,
                area=form.cleaned_data["area"],
                altitude_m=form.cleaned_data["altitude_m"],
            )
        except RescueError as exc:
            form.add_error(None, str(exc))
        else:
            return redirect("session", session_id=session.pk)
    available = service_vehicles_matching(service)
    stations = {v.station for v in available} or set(Station.objects.all())
    return render(
        request,
        "services/rescue_request.html",
        {
            "service": service,
            "form": form,
            "available": available,
            "map": {
                "stations": [
                    {"name": s.name, "lat": s.lat, "lon": s.lon}
                    for s in sorted(stations, key=lambda s: s.name)
                ],
                "tiles": settings.IOUV_MAP_TILES_URL,
            },
        },
    )


def _log_lines(session: Session) -> list[dict[str, Any]]:
    """The newest log events, as the session page lists them."""
    lines = []
    for event in session.events.order_by("-seq")[:30]:
        data = event.data if isinstance(event.data, dict) else {}
        detail = data.get("reason") or data.get("cause") or data.get("to") or ""
        lines.append(
            {"at": event.created_at, "label": event.kind.replace("_", " "), "detail": detail}
        )
    return lines


def _own_session(request: HttpRequest, session_id: str) -> Session:
    session = get_object_or_404(Session.objects.select_related("service"), pk=session_id)
    if session.user_id != request.user.pk:
        raise Http404("no such session")
    return session


# Pages and answers that carry a signed grant must not be stored by the browser or a
# proxy (Cache-Control: no-store): a grant kept in a cache could be read there and
# used, by someone else, until it expires.
@never_cache
@login_required
def session_page(request: HttpRequest, session_id: str) -> HttpResponse:
    """The user task: the controller for the session's vehicle."""
    session = _own_session(request, session_id)
    task = None
    if session.state not in FINAL:
        try:
            task = user_task_json(
                grant_issue(session=session, user=request.user, role=_role(session)),
                request=request,
            )
        except DeploymentError as exc:
            if session.service.mode == Service.Mode.SYNCHRONOUS:
                messages.error(request, str(exc))
    mission = Mission.objects.filter(pk=session.pk).first()
    if mission is not None:
        return render(
            request,
            "services/mission.html",
            {
                "session": session,
                "summary": session_summary(session),
                "user_task": task,
                "mission": mission_json(mission),
                "events": _log_lines(session),
                "tiles": settings.IOUV_MAP_TILES_URL,
            },
        )
    return render(
        request,
        "services/session.html",
        {
            "session": session,
            "summary": session_summary(session),
            "user_task": task,
            "events": _log_lines(session),
        },
    )


@never_cache
@login_required
@require_POST
def session_grant(request: HttpRequest, session_id: str) -> JsonResponse:
    """A fresh grant to reconnect (JSON for the controller script)."""
    session = _own_session(request, session_id)
    try:
        task = grant_issue(session=session, user=request.user, role=_role(session))
        return JsonResponse(user_task_json(task, request=request))
    except DeploymentError as exc:
        return JsonResponse({"error": {"code": "session_over", "message": str(exc)}}, status=409)


def _role(session: Session) -> str:
    # An autonomous mission is watched, never steered: a viewer's link cannot arm
    # the vehicle's link-loss fail-safe, so closing the page does not abort it.
    return "viewer" if session.service.mode == Service.Mode.ASYNCHRONOUS else "controller"


@login_required
def session_mission(request: HttpRequest, session_id: str) -> JsonResponse:
    """The mission's live state for the map (the session's user, or a monitor)."""
    session = get_object_or_404(Session, pk=session_id)
    if session.user_id != request.user.pk and not request.user.has_perm("fleet.view_fleet"):
        raise Http404("no such session")
    mission = get_object_or_404(Mission.objects.select_related("session"), pk=session_id)
    return JsonResponse(mission_json(mission))


@login_required
@require_POST
def session_finish(request: HttpRequest, session_id: str) -> HttpResponse:
    """The user ends the session on purpose."""
    session = _own_session(request, session_id)
    if session.state not in FINAL:
        session_end(session=session, reason="ended by the user", by_user=True)
        messages.success(request, f"{session.service.name}: session ended.")
    return redirect("catalog")


@login_required
@permission_required("services.stop_session", raise_exception=True)
@require_POST
def session_stop(request: HttpRequest, session_id: str) -> HttpResponse:
    """A monitor's kill switch: revoke the grant, the vehicle performs its safe action."""
    session = get_object_or_404(Session.objects.select_related("service"), pk=session_id)
    if session.state not in FINAL:
        session_revoke(
            session=session,
            reason=f"stopped by monitor {request.user.get_username()}",
            action=session.service.failsafe_action,
        )
    if request.headers.get("accept", "").startswith("application/json"):
        return JsonResponse({"session": session_summary(Session.objects.get(pk=session.pk))})
    return redirect("monitor")


def _spectate_service(request: HttpRequest) -> Service:
    service = Service.objects.filter(workflow="spectate", is_active=True).first()
    if service is None or not user_can_use(request.user, service):
        raise Http404("spectating is not open to you")
    return service


@login_required
def spectate(request: HttpRequest) -> HttpResponse:
    """Vehicles streaming video in a live session, to watch."""
    _spectate_service(request)
    return render(request, "services/spectate.html", {"sessions": sessions_spectatable()})


@never_cache
@login_required
def spectate_session(request: HttpRequest, session_id: str) -> HttpResponse:
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
        "services/session.html",
        {
            "session": session,
            "summary": session_summary(session),
            "user_task": user_task_json(task, request=request),
            "events": _log_lines(session),
            "spectating": True,
        },
    )


@login_required
@permission_required("fleet.view_fleet", raise_exception=True)
def monitor(request: HttpRequest) -> HttpResponse:
    """The live fleet and every live session, with a stop button per session."""
    return render(
        request,
        "services/monitor.html",
        {"can_stop": request.user.has_perm("services.stop_session")},
    )


def healthz(request: HttpRequest) -> JsonResponse:
    """Liveness for proxies and the demo script: answers once the database does."""
    with connection.cursor() as cursor:
        cursor.execute("SELECT 1")
    return JsonResponse({"ok": True, "database": connection.vendor})
