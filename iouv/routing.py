"""WebSocket routes, kept apart from asgi.py so tests can build the same stack."""

from django.urls import path

from fleet.consumers import FleetFeedConsumer
from fleet.uplink import AgentUplinkConsumer
from services.consumers import RelayConsumer, SessionFeedConsumer, SessionsMonitorConsumer

# Not behind the browser origin check: these authenticate inside the socket (agents
# with their credential, relayed clients with their grant) and use no cookie.
self_authenticating_websocket_urlpatterns: list = [
    path("ws/agent/", AgentUplinkConsumer.as_asgi()),
    # The relay authenticates by the signed grant in its first frame, not by cookie,
    # so API programs can use it and no cross-site request can ride on a session.
    path("ws/relay/<uuid:session_id>/", RelayConsumer.as_asgi()),
]

# Opened by browsers; wrapped in the origin validator and session auth by asgi.py.
browser_websocket_urlpatterns = [
    path("ws/fleet/", FleetFeedConsumer.as_asgi()),
    path("ws/sessions/", SessionsMonitorConsumer.as_asgi()),
    path("ws/sessions/<uuid:session_id>/", SessionFeedConsumer.as_asgi()),
]
