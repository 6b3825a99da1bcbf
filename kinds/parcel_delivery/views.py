"""The delivery's own pages: its live state for the map, and the recipient's page."""

from __future__ import annotations

from django.conf import settings
from django.contrib.auth.decorators import login_required
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import get_object_or_404, render
from django.views.decorators.cache import never_cache

from accounts.users import AuthenticatedHttpRequest
from kinds.parcel_delivery.models import Delivery
from kinds.parcel_delivery.presentation import delivery_json
from services.kit import session_watched


@login_required
def delivery_state(request: AuthenticatedHttpRequest, session_id: str) -> JsonResponse:
    """The delivery's live state (its user, or a monitor)."""
    session_watched(request, session_id)
    delivery = get_object_or_404(Delivery.objects.select_related("session"), pk=session_id)
    return JsonResponse(delivery_json(delivery))


def _by_token(token: str) -> Delivery:
    delivery = Delivery.objects.select_related("session").filter(tracking_token=token).first()
    if delivery is None:
        raise Http404("no such parcel")
    return delivery


@never_cache  # the link is the key: no cache keeps the page
def track(request: HttpRequest, token: str) -> HttpResponse:
    """The recipient's page: where the parcel is and when it arrives (no account)."""
    delivery = _by_token(token)
    return render(
        request,
        "parcel_delivery/track.html",
        {
            "delivery": delivery_json(delivery, public=True),
            "token": token,
            "tiles": settings.IOUV_MAP_TILES_URL,
        },
    )


@never_cache
def track_state(request: HttpRequest, token: str) -> JsonResponse:
    """The recipient's page's live state."""
    return JsonResponse(delivery_json(_by_token(token), public=True))
