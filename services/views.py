"""Portal views: thin, they parse, call a service function and render."""

from __future__ import annotations

from django.contrib.auth.decorators import login_required
from django.db import connection
from django.http import HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import render

from accounts.roles import user_roles
from services.grants import services_for_user


@login_required
def catalog(request: HttpRequest) -> HttpResponse:
    """The services this user may request."""
    services = services_for_user(request.user).prefetch_related("roles")
    return render(
        request,
        "services/catalog.html",
        {"services": services, "roles": sorted(user_roles(request.user))},
    )


def healthz(request: HttpRequest) -> JsonResponse:
    """Liveness for proxies and the demo script: answers once the database does."""
    with connection.cursor() as cursor:
        cursor.execute("SELECT 1")
    return JsonResponse({"ok": True, "database": connection.vendor})
