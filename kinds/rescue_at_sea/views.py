"""The rescue's own pages: the mission's live state for the map."""

from __future__ import annotations

from django.contrib.auth.decorators import login_required
from django.http import JsonResponse
from django.shortcuts import get_object_or_404

from accounts.users import AuthenticatedHttpRequest
from kinds.rescue_at_sea.models import Mission
from kinds.rescue_at_sea.presentation import mission_json
from services.kit import session_watched


@login_required
def session_mission(request: AuthenticatedHttpRequest, session_id: str) -> JsonResponse:
    """The mission's live state for the map (the session's user, or a monitor)."""
    session_watched(request, session_id)
    mission = get_object_or_404(Mission.objects.select_related("session"), pk=session_id)
    return JsonResponse(mission_json(mission))
