"""ICE servers for a session's WebRTC connection: STUN, and TURN with short-lived
credentials.

TURN credentials follow the "TURN REST API" shared-secret scheme that coturn implements
(``use-auth-secret`` with ``static-auth-secret``): the username is
``<expiry unix time>:<name>`` and the password is
``base64(HMAC-SHA1(secret, username))``. The TURN server recomputes the password from
the secret it shares with the platform and refuses a username whose expiry has passed,
so nothing per session is stored on either side and a leaked credential dies on its own.

The platform hands one set to the user (in the user task) and one to the vehicle (with
each WebRTC offer relayed to it), named after the session so the TURN server's log says
whose traffic it relayed. Each set expires with the grant it comes with (the user task's,
or the one the relayed connection authenticated with), ``IOUV_TURN_TTL_S`` at the most:
whoever held a user task, a viewer included, can open no TURN allocation after that
grant's end. coturn checks a credential only when an allocation is made, so a connection
already relayed keeps its allocation as long as it refreshes it; a reconnect comes with a
fresh grant and fresh credentials.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import math
import time
from typing import Any

from django.conf import settings


def turn_credentials(
    secret: str, name: str, *, ttl_s: int, now: float | None = None
) -> tuple[str, str]:
    """(username, password) for the TURN REST scheme, valid ``ttl_s`` seconds from
    ``now`` (default: the current time). ``name`` must not contain ``:``."""
    if ":" in name:
        raise ValueError("a TURN credential name may not contain ':'")
    expiry = int((time.time() if now is None else now) + ttl_s)
    username = f"{expiry}:{name}"
    digest = hmac.new(secret.encode(), username.encode(), hashlib.sha1).digest()
    return username, base64.b64encode(digest).decode()


def ice_servers_for(
    name: str, *, expires_at: float | None = None, now: float | None = None
) -> list[dict[str, Any]]:
    """The ICE servers of the platform's configuration as an ``RTCIceServer`` list:
    ``IOUV_STUN_URLS`` as is, ``IOUV_TURN_URLS`` with fresh credentials for ``name``
    (a session id) when ``IOUV_TURN_SECRET`` is set, valid ``IOUV_TURN_TTL_S`` and no
    later than ``expires_at`` (Unix seconds: the grant they come with). A grant already
    over gets no TURN server. Empty when none is configured: peers then only find each
    other on a network they share."""
    current = time.time() if now is None else now
    servers: list[dict[str, Any]] = []
    if settings.IOUV_STUN_URLS:
        servers.append({"urls": list(settings.IOUV_STUN_URLS)})
    ttl_s = settings.IOUV_TURN_TTL_S
    if expires_at is not None:
        ttl_s = min(ttl_s, math.floor(expires_at - current))
    if settings.IOUV_TURN_URLS and settings.IOUV_TURN_SECRET and ttl_s > 0:
        username, credential = turn_credentials(
            settings.IOUV_TURN_SECRET, name, ttl_s=ttl_s, now=current
        )
        servers.append(
            {"urls": list(settings.IOUV_TURN_URLS), "username": username, "credential": credential}
        )
    return servers
