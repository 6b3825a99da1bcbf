"""Where a request came from: the client's address that lockouts and rate limits count by.

Without a proxy it is the peer of the connection (``REMOTE_ADDR``). Behind nginx
(``BEHIND_PROXY``) every request comes from nginx itself, so the address is the last
entry of ``X-Forwarded-For``: nginx's ``$proxy_add_x_forwarded_for`` appends the address
it was connected from to whatever the client sent, and only that last entry is nginx's
word (the ones before it are the client's, and could be anything). One proxy in front
is the layout of docs/operations.md; a second one (a load balancer before nginx) would
need nginx's realip module so that nginx's own ``$remote_addr`` is the client's.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from typing import Any

from django.conf import settings
from django.http import HttpRequest


def client_address(request: HttpRequest) -> str | None:
    """The client's IP address as text, None when there is none to read (a request
    made in process, a proxy on a Unix socket without ``BEHIND_PROXY``).

    Used by django-axes (``AXES_CLIENT_IP_CALLABLE``) and by the rate limits
    (services.web.throttle), so both count the same client."""
    if settings.BEHIND_PROXY:
        forwarded = request.META.get("HTTP_X_FORWARDED_FOR", "")
        last = forwarded.rsplit(",", 1)[-1].strip()
        if last:
            return _address(last)
    return _address(str(request.META.get("REMOTE_ADDR") or ""))


def _address(text: str) -> str | None:
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        return None


def client_address_of_scope(scope: Mapping[str, Any]) -> str | None:
    """:func:`client_address` of a WebSocket's ASGI ``scope`` (its ``client`` and its
    headers)."""
    if settings.BEHIND_PROXY:
        for name, value in scope.get("headers") or ():
            if name == b"x-forwarded-for":
                last = value.decode("latin-1").rsplit(",", 1)[-1].strip()
                if last:
                    return _address(last)
    client = scope.get("client") or ("", 0)
    return _address(str(client[0] or ""))
