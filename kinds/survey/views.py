"""The survey's own pages: its live state for the map, the mosaic, and its KMZ."""

from __future__ import annotations

from django.contrib.auth.decorators import login_required
from django.http import Http404, HttpResponse, JsonResponse
from django.shortcuts import get_object_or_404

from accounts.users import AuthenticatedHttpRequest
from kinds.survey.models import Survey
from kinds.survey.mosaic import Mosaic, kmz
from kinds.survey.presentation import survey_json
from services.kit import session_watched


def _survey(request: AuthenticatedHttpRequest, session_id: str) -> Survey:
    session_watched(request, session_id)
    return get_object_or_404(Survey.objects.select_related("session__service"), pk=session_id)


@login_required
def survey_state(request: AuthenticatedHttpRequest, session_id: str) -> JsonResponse:
    """The survey's live state (its user, or a monitor)."""
    return JsonResponse(survey_json(_survey(request, session_id)))


@login_required
def survey_mosaic(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """The mosaic picture (PNG, north up, over the state's ``mosaic.bounds``)."""
    survey = _survey(request, session_id)
    if survey.mosaic is None:
        raise Http404("no mosaic yet")
    return HttpResponse(bytes(survey.mosaic), content_type="image/png")


@login_required
def survey_kmz(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """The mosaic as a KMZ ground overlay, for GIS tools (QGIS, Google Earth)."""
    survey = _survey(request, session_id)
    if survey.mosaic is None or survey.mosaic_bounds is None:
        raise Http404("no mosaic yet")
    mosaic = Mosaic(png=bytes(survey.mosaic), bounds=list(survey.mosaic_bounds), size=(0, 0))
    body = kmz(mosaic, name=f"{survey.session.service.name} {str(survey.pk)[:8]}")
    response = HttpResponse(body, content_type="application/vnd.google-earth.kmz")
    response["Content-Disposition"] = f'attachment; filename="survey-{str(survey.pk)[:8]}.kmz"'
    return response
