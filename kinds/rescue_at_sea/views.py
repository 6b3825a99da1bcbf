"""The rescue's own pages: the mission's live state for the map."""

from __future__ import annotations

from django.contrib.auth.decorators import login_required
from django.http import Http404, HttpRequest, JsonResponse
from django.shortcuts import get_object_or_404

from kinds.rescue_at_sea.models import Mission
from kinds.rescue_at_sea.presentation import mission_json
from services.models import Session


@login_required
def session_mission(request: HttpRequest, session_id: str) -> JsonResponse:
    """The mission's live state for the map (the session's user, or a monitor)."""
    session = get_object_or_404(Session, pk=session_id)
    if session.user_id != request.user.pk and not request.user.has_perm("fleet.view_fleet"):
        raise Http404("no such session")
    mission = get_object_or_404(Mission.objects.select_related("session"), pk=session_id)
    return JsonResponse(mission_json(mission))
