"""Portal views: thin, they parse, call a service function and render."""

from __future__ import annotations

import functools

from django.conf import settings
from django.contrib import messages
from django.contrib.auth.decorators import login_required, permission_required
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import get_object_or_404, redirect, render
from django.views.decorators.cache import cache_control, never_cache
from django.views.decorators.http import require_GET, require_POST

from accounts.roles import user_roles
from accounts.users import AuthenticatedHttpRequest
from agents.geography import MASK_PATH
from fleet.models import Station
from services.kinds import RequestError, ServiceKind, UnknownKind, kind_of
from services.models import Service, Session
from services.sessions.deployment import (
    DeploymentError,
    NotAssignedYet,
    grant_issue,
    user_task_json,
)
from services.sessions.ending import session_end_by_user, session_ended_words, session_revoke
from services.sessions.feasibility import request_map_default
from services.sessions.grants import services_for_user, services_usable
from services.sessions.matching import AssignmentError
from services.sessions.request import service_request
from services.sessions.selectors import service_vehicles_matching, session_summary
from services.sessions.states import FINAL, SessionStateError
from services.web.throttle import throttled
from services.web.watching import log_lines, session_vehicle_names


def _kind(service: Service) -> ServiceKind:
    try:
        return kind_of(service)
    except UnknownKind:
        raise Http404("this service's kind is not installed") from None


@login_required
def catalog(request: AuthenticatedHttpRequest) -> HttpResponse:
    """The services this user may request, and their own live sessions."""
    entries = []
    for service in services_for_user(request.user).prefetch_related("roles"):
        try:
            kind = kind_of(service)
        except UnknownKind:
            continue  # an offer whose kind is not installed here cannot be used
        entries.append({"service": service, "kind": kind, "url": kind.entry_url(service)})
    mine = (
        Session.objects.filter(user=request.user).exclude(state__in=FINAL).select_related("service")
    )
    return render(
        request,
        "services/catalog.html",
        {"entries": entries, "roles": sorted(user_roles(request.user)), "live": mine},
    )


@login_required
@throttled("session_request", methods=("POST",))
def service_request_page(request: AuthenticatedHttpRequest, slug: str) -> HttpResponse:
    """The request page of one service (its kind's form); a valid POST opens the
    session (services.sessions.request: the same path as the API) and shows its page."""
    service = services_usable(request.user).filter(slug=slug).first()
    if service is None:
        raise Http404("no such service")
    if not service.usable:
        raise Http404("no such service for you")
    kind = _kind(service)
    if not kind.requestable or kind.form_class is None:
        return redirect(kind.entry_url(service))
    form = kind.form_class(request.POST or None)
    if request.method == "POST" and form.is_valid():
        try:
            opened = service_request(
                user=request.user,
                service=service,
                request=kind.request_from_form(form),
                usable=True,  # checked above, with the service
            )
        except RequestError as exc:
            # On the field it names if the form has one (params.area -> area).
            name = (exc.field or "").removeprefix("params.")
            form.add_error(name if name in form.fields else None, str(exc))
        except (AssignmentError, DeploymentError) as exc:
            messages.error(request, f"Not possible right now: {exc}")
        else:
            return redirect("session", session_id=opened.session.pk)
    # The map opens where the service can be given, and shows how far its vehicles
    # reach (services.sessions.feasibility): a request beyond that is refused at once.
    return render(
        request,
        kind.request_template,
        {
            "service": service,
            "kind": kind,
            "form": form,
            "available": service_vehicles_matching(service, kind.request_role(service)),
            "map": {
                **(kind.request_map(service) or request_map_default(kind, service)),
                "tiles": settings.IOUV_MAP_TILES_URL,
            },
        },
    )


def _own_session(request: AuthenticatedHttpRequest, session_id: str) -> Session:
    session = get_object_or_404(Session.objects.select_related("service"), pk=session_id)
    if session.user_id != request.user.pk:
        raise Http404("no such session")
    return session


# Pages and answers that carry a signed grant must not be stored by the browser or a
# proxy (Cache-Control: no-store): a grant kept in a cache could be read there and
# used, by someone else, until it expires.
@never_cache
@login_required
@throttled("grant")  # every view of the page mints a grant
def session_page(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """The user task: the page the session's kind opens on, with a fresh grant."""
    session = _own_session(request, session_id)
    kind = _kind(session.service)
    task = None
    if session.state not in FINAL:
        try:
            task = user_task_json(
                grant_issue(session=session, user=request.user, role=kind.grant_role(session)),
                request=request,
            )
        except DeploymentError as exc:
            if kind.user_drives:
                messages.error(request, str(exc))
    return render(
        request,
        kind.session_template,
        {
            "session": session,
            "summary": session_summary(session),
            "session_vehicles": session_vehicle_names(session),
            "user_task": task,
            # Open but no vehicle yet: the page asks for its grant once one is assigned.
            "session_open": session.state not in FINAL,
            "events": log_lines(session),
            **kind.session_context(request=request, session=session),
        },
    )


@never_cache
@login_required
@require_POST
@throttled("grant", json=True, done_if_ok=True)
def session_grant(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """A fresh grant to reconnect (JSON for the controller script)."""
    session = _own_session(request, session_id)
    try:
        role = _kind(session.service).grant_role(session)
        task = grant_issue(session=session, user=request.user, role=role)
        return JsonResponse(user_task_json(task, request=request))
    except NotAssignedYet as exc:
        # The page waits and asks again: the kind's workflow is still finding a vehicle.
        return JsonResponse({"error": {"code": "no_vehicle_yet", "message": str(exc)}}, status=409)
    except DeploymentError as exc:
        return JsonResponse({"error": {"code": "session_over", "message": str(exc)}}, status=409)


@login_required
@require_POST
def session_finish(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """The user ends the session on purpose."""
    session = _own_session(request, session_id)
    if session.state in FINAL:
        messages.info(request, f"{session.service.name}: the session was already over.")
        return redirect("catalog")
    try:
        session_end_by_user(session=session)
    except SessionStateError:
        # Ended meanwhile (a monitor, its workflow): nothing left to end.
        messages.info(request, f"{session.service.name}: the session was already over.")
    else:
        messages.success(request, session_ended_words(session))
    return redirect("catalog")


@login_required
@permission_required("services.stop_session", raise_exception=True)
@require_POST
def session_stop(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """A monitor's kill switch: revoke the grant, the vehicle performs its safe action."""
    session = get_object_or_404(Session.objects.select_related("service"), pk=session_id)
    if session.state not in FINAL:
        session_revoke(
            session=session,
            reason=f"stopped by a monitor ({request.user.get_username()})",
            action=session.service.failsafe_action,
        )
    if request.headers.get("accept", "").startswith("application/json"):
        return JsonResponse({"session": session_summary(Session.objects.get(pk=session.pk))})
    return redirect("monitor")


@login_required
@permission_required("fleet.view_fleet", raise_exception=True)
def monitor(request: AuthenticatedHttpRequest) -> HttpResponse:
    """The live fleet (a table and a map) and every live session, with a stop button per
    session."""
    stations = Station.objects.order_by("name")
    return render(
        request,
        "services/monitor.html",
        {
            "can_stop": request.user.has_perm("services.stop_session"),
            "map": {
                "stations": [{"name": s.name, "lat": s.lat, "lon": s.lon} for s in stations],
                "tiles": settings.IOUV_MAP_TILES_URL,
            },
        },
    )


#: How long browsers and proxies may keep the land mask: it changes only with a release
#: of the platform (a new ``agents/geography/data/land.geo.json``).
LAND_MAP_MAX_AGE_S = 7 * 24 * 3600


@functools.cache
def _land_map_bytes() -> bytes:
    # Read once per process: the file is part of the installed code.
    return MASK_PATH.read_bytes()


@cache_control(public=True, max_age=LAND_MAP_MAX_AGE_S)
@require_GET
def land_map(request: HttpRequest) -> HttpResponse:
    """The packaged land mask (GeoJSON: a region's box and its land polygons, © OpenStreetMap
    contributors, ODbL) that the maps draw as land and sea when no tile server is
    configured. Public, like any map tile: the recipient's tracking page shows it too."""
    return HttpResponse(_land_map_bytes(), content_type="application/geo+json")
