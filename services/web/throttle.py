"""Rate limits on what costs the platform something for each call: requesting a session,
minting a grant, forwarding a WebRTC offer (each writes the session's log or reaches a
vehicle).

Each action has a budget per user and one per client address (``IOUV_RATE_LIMITS``),
counted by django-ratelimit in Django's cache: Redis with ``REDIS_URL``, so every platform
process counts together; the process's memory otherwise. A call over either budget is
refused with :class:`Throttled`, which says how long until the window ends: the API
answers 429 ``rate_limited`` with ``Retry-After``, the portal a 429 page or JSON, the
relay an ``error`` frame. Nothing is done for a refused call.

The counter is a fixed window (django-ratelimit's): a client may spend a whole budget at
the end of one window and another at the start of the next.
"""

from __future__ import annotations

import functools
import ipaddress
import logging
from collections.abc import Callable
from typing import Any, TypeVar, cast

from django.conf import settings
from django.http import HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import render
from django_ratelimit.core import get_usage

from accounts.addresses import client_address

log = logging.getLogger(__name__)

#: The actions that are limited, and what the refusal calls them.
ACTIONS = {
    "session_request": "session requests",
    "grant": "grants",
    "webrtc_offer": "WebRTC offers",
}


class Throttled(Exception):
    """Over the budget of ``action``; ``retry_after_s``: until the window ends."""

    def __init__(self, action: str, *, per: str, limit: int, window_s: int, retry_after_s: int):
        self.action = action
        self.retry_after_s = max(1, retry_after_s)
        what = ACTIONS.get(action, action)
        super().__init__(
            f"too many {what}: at most {limit} per {window_s} s from one {per}; "
            f"try again in {self.retry_after_s} s"
        )


def _rate(action: str, per: str) -> str | None:
    """``"N/Ss"``-style budget of ``action`` per ``user`` or ``address``; None: unlimited."""
    rates: dict[str, dict[str, str]] = settings.IOUV_RATE_LIMITS
    rate = rates.get(action, {}).get(per, "")
    return None if rate.lower() in ("", "off") else rate


def throttle_check(*, action: str, user_id: Any | None, address: str | None) -> None:
    """Count one ``action`` of ``user_id`` from ``address`` (either may be None: not
    counted by it); raise :class:`Throttled` when that makes it over either budget.

    The counts go up even for a refused call: a client that keeps trying keeps its
    window full, not a fresh budget every window."""
    for per, value in (("user", user_id), ("address", address)):
        usage = _usage(action, per, value, increment=True)
        if usage is not None and usage["count"] > usage["limit"]:
            raise _throttled(action, per, usage)


def throttle_peek(*, action: str, user_id: Any | None, address: str | None) -> None:
    """Raise :class:`Throttled` if one more ``action`` would be over a budget, without
    counting it (:func:`throttle_count` counts it once it was done)."""
    for per, value in (("user", user_id), ("address", address)):
        usage = _usage(action, per, value, increment=False)
        if usage is not None and usage["count"] >= usage["limit"]:
            raise _throttled(action, per, usage)


def throttle_count(*, action: str, user_id: Any | None, address: str | None) -> None:
    """Count one ``action`` that was done (see :func:`throttle_peek`)."""
    for per, value in (("user", user_id), ("address", address)):
        _usage(action, per, value, increment=True)


def _usage(action: str, per: str, value: Any | None, *, increment: bool) -> dict[str, Any] | None:
    """django-ratelimit's usage of ``action``'s budget ``per`` for ``value``: ``count``,
    ``limit``, ``time_left``, ``rate``; None when not limited (no value, no budget, or
    the cache cannot be reached: then the call goes through, and the log says so)."""
    rate = _rate(action, per)
    if value is None or rate is None:
        return None
    try:
        usage = get_usage(
            None,
            group=f"iouv.{action}.{per}",
            key=lambda _group, _request: str(value),
            rate=rate,
            increment=increment,
        )
    except Exception as exc:  # Redis away: better serve than refuse everyone
        log.warning("rate limit %s per %s not checked: %s", action, per, exc)
        return None
    if usage is None or usage["time_left"] < 0:  # off, or the cache did not count
        return None
    return {**usage, "rate": rate}


def _throttled(action: str, per: str, usage: dict[str, Any]) -> Throttled:
    limit, _, window = str(usage["rate"]).partition("/")
    return Throttled(
        action,
        per=per,
        limit=int(limit),
        window_s=_seconds(window),
        retry_after_s=int(usage["time_left"]),
    )


def _seconds(window: str) -> int:
    units = {"s": 1, "m": 60, "h": 3600, "d": 86400}
    if window and window[-1] in units:
        return int(window[:-1] or 1) * units[window[-1]]
    return int(window or 1)


def counted_address(address: str | None) -> str | None:
    """``address`` as the per-address budgets count it: None (not counted) for none
    and for the platform's own machine. A loopback client is a local program (a health check, a
    script beside the platform), or every client at once when a proxy in front does not
    pass their addresses on (BEHIND_PROXY unset): one budget shared by all of them would
    refuse everyone, so only the per-user budgets apply there."""
    if address is None or ipaddress.ip_address(address).is_loopback:
        return None
    return address


def request_keys(request: HttpRequest) -> dict[str, Any]:
    """The ``user_id`` (None unless logged in) and ``address`` (accounts.addresses, as
    :func:`counted_address` counts it) an HTTP request is counted by."""
    user = getattr(request, "user", None)
    user_id = user.pk if user is not None and user.is_authenticated else None
    return {"user_id": user_id, "address": counted_address(client_address(request))}


def throttled_response(request: HttpRequest, exc: Throttled, *, json: bool) -> HttpResponse:
    """429 with ``Retry-After``: JSON ``{"error": {"code": "rate_limited", ...}}`` for
    scripts, else a page."""
    response: HttpResponse
    if json:
        response = JsonResponse(
            {"error": {"code": "rate_limited", "message": str(exc)}}, status=429
        )
    else:
        response = render(request, "services/throttled.html", {"message": str(exc)}, status=429)
    response["Retry-After"] = str(exc.retry_after_s)
    return response


_View = TypeVar("_View", bound=Callable[..., HttpResponse])


def throttled(
    action: str, *, json: bool = False, methods: tuple[str, ...] = (), done_if_ok: bool = False
) -> Callable[[_View], _View]:
    """A portal view counted as ``action`` (only for ``methods``, if given): over the
    budget it answers :func:`throttled_response` instead of running. ``done_if_ok``:
    only an answer of 2xx counts (a grant the controller asks for while the session
    waits for a vehicle is not minted, and its page asks again every few seconds)."""

    def decorate(view: _View) -> _View:
        @functools.wraps(view)
        def limited(request: HttpRequest, *args: Any, **kwargs: Any) -> HttpResponse:
            if methods and request.method not in methods:
                return view(request, *args, **kwargs)
            keys = request_keys(request)
            try:
                if done_if_ok:
                    throttle_peek(action=action, **keys)
                else:
                    throttle_check(action=action, **keys)
            except Throttled as exc:
                return throttled_response(request, exc, json=json)
            response = view(request, *args, **kwargs)
            if done_if_ok and 200 <= response.status_code < 300:
                throttle_count(action=action, **keys)
            return response

        return cast(_View, limited)

    return decorate
