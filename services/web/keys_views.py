"""The platform's public signing keys, published as a JWK Set for agents and clients."""

from __future__ import annotations

from django.http import HttpRequest, JsonResponse
from django.views.decorators.cache import cache_control
from django.views.decorators.http import require_GET

from services.sessions.signing import platform_jwks

#: Short, so a rotation (a new key added) reaches fetchers within minutes, while the
#: previous key stays listed far longer than this (docs/protocol.md, "Key rotation").
JWKS_MAX_AGE_S = 300


@cache_control(public=True, max_age=JWKS_MAX_AGE_S)
@require_GET
def jwks(request: HttpRequest) -> JsonResponse:
    """``/.well-known/jwks.json``: the current and previous public keys (RFC 7517).

    Public on purpose (public keys; agents fetch it at enrolment without an account).
    """
    return JsonResponse(platform_jwks())
