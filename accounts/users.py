"""The platform's user, as code and the type checker see it.

The platform keeps Django's own user model (``auth.User``; AUTH_USER_MODEL is not set),
so code acting for a signed-in user takes a :class:`User`, whose roles are its groups
(accounts.roles). A view that only signed-in users reach (``login_required``, or the
API's bearer token) takes an :class:`AuthenticatedHttpRequest`, whose ``user`` is a
:class:`User` rather than ``User | AnonymousUser``.
"""

from __future__ import annotations

from django.contrib.auth.models import User
from django.http import HttpRequest

__all__ = ["AuthenticatedHttpRequest", "User"]


class AuthenticatedHttpRequest(HttpRequest):
    """An HttpRequest whose user has signed in. Only an annotation: Django makes the
    requests; the view's decorator is what makes this true."""

    user: User
