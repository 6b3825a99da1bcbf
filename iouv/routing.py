"""WebSocket routes, kept apart from asgi.py so tests can build the same stack."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeAlias, cast

from django.urls import path, re_path

from fleet.consumers import FleetFeedConsumer
from fleet.uplink import AgentUplinkConsumer
from services.web.consumers import RelayConsumer, SessionFeedConsumer, SessionsMonitorConsumer

if TYPE_CHECKING:
    from channels.routing import URLRouter, _ExtendedURLPattern
    from channels.utils import _ChannelApplication

    #: What Channels' URLRouter takes.
    WebsocketRoutes: TypeAlias = list[_ExtendedURLPattern | URLRouter]


def websocket_path(
    route: str, app: _ChannelApplication, *, regex: bool = False
) -> _ExtendedURLPattern:
    """Django's ``path()`` (``re_path()`` with ``regex``) routing to an ASGI application,
    as Channels' URLRouter takes it. Only the types need this: django-stubs types
    ``path()`` for views, the Channels stubs want a pattern whose callback is an app."""
    make = re_path if regex else path
    return cast("_ExtendedURLPattern", make(route, cast(Any, app)))


# Not behind the browser origin check: these authenticate inside the socket (agents
# with their credential, relayed clients with their grant) and use no cookie.
self_authenticating_websocket_urlpatterns: WebsocketRoutes = [
    websocket_path("ws/agent/", AgentUplinkConsumer.as_asgi()),
    # The relay authenticates by the signed grant in its first frame, not by cookie,
    # so API programs can use it and no cross-site request can ride on a session.
    websocket_path("ws/relay/<uuid:session_id>/", RelayConsumer.as_asgi()),
]

# Opened by browsers; wrapped in the origin validator and session auth by asgi.py.
browser_websocket_urlpatterns: WebsocketRoutes = [
    websocket_path("ws/fleet/", FleetFeedConsumer.as_asgi()),
    websocket_path("ws/sessions/", SessionsMonitorConsumer.as_asgi()),
    websocket_path("ws/sessions/<uuid:session_id>/", SessionFeedConsumer.as_asgi()),
]
