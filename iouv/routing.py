"""WebSocket routes, kept apart from asgi.py so tests can build the same stack."""

from django.urls import path

from fleet.consumers import FleetFeedConsumer
from fleet.uplink import AgentUplinkConsumer

# Opened by vehicle agents; authenticated by vehicle credential inside the socket.
agent_websocket_urlpatterns: list = [
    path("ws/agent/", AgentUplinkConsumer.as_asgi()),
]

# Opened by browsers; wrapped in the origin validator and session auth by asgi.py.
browser_websocket_urlpatterns = [
    path("ws/fleet/", FleetFeedConsumer.as_asgi()),
]
