"""Login lockout (django-axes): too many failed log-ins lock the address and the account.

django-axes counts failed log-ins on every form that authenticates through Django (the
portal's login page, the admin's) and, once ``AXES_FAILURE_LIMIT`` failures came from
one address or named one account, refuses further attempts from that address or for
that account for ``AXES_COOLOFF_TIME`` (settings: ``IOUV_LOGIN_FAILURE_LIMIT``,
``IOUV_LOGIN_COOLOFF_S``), the right password included. A refused attempt is decided
before any password is hashed, so a flood of wrong passwords stops costing the platform
a hash each (PBKDF2's several hundred milliseconds of CPU) once it is locked out.

The API has no password endpoint: it takes only bearer tokens (accounts.tokens), 256-bit
random secrets that cannot be guessed, and its requests are limited per address
(services.web.throttle).
"""

from __future__ import annotations

from typing import Any

from axes.backends import AxesStandaloneBackend
from axes.helpers import get_cool_off
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render


class LoginLockoutBackend(AxesStandaloneBackend):  # type: ignore[misc]  # axes is untyped
    """django-axes' check, first in ``AUTHENTICATION_BACKENDS``: a locked-out address or
    account is refused before the password is looked at.

    Only log-ins of an HTTP request are counted and checked. A call without a request
    is the platform's own code (a management command, a test's ``Client.login``), not
    a client guessing passwords; axes would refuse it with an error."""

    def authenticate(
        self,
        request: HttpRequest | None,
        username: str | None = None,
        password: str | None = None,
        **kwargs: Any,
    ) -> None:
        if request is None:
            return None
        super().authenticate(request, username=username, password=password, **kwargs)
        return None


def login_locked_out(
    request: HttpRequest, original_response: HttpResponse | None = None, credentials: Any = None
) -> HttpResponse:
    """The answer to a locked-out log-in (``AXES_LOCKOUT_CALLABLE``): 429 with
    ``Retry-After`` (the cool-off, in seconds), on a page that says so."""
    cool_off = get_cool_off(request)
    seconds = int(cool_off.total_seconds()) if cool_off else 0
    response = render(
        request,
        "accounts/locked_out.html",
        {"minutes": max(1, round(seconds / 60)) if seconds else None},
        status=429,
    )
    if seconds:
        response["Retry-After"] = str(seconds)
    return response
