"""Spectating, as a service kind: watch the camera of a vehicle in someone's session."""

from __future__ import annotations

from collections.abc import Mapping

from django.urls import reverse

from services.kit import DemoService, ServiceKind
from services.models import Service


class Spectate(ServiceKind):
    """Any number of viewers watch a live session's vehicle: the same video and
    telemetry as its user, view-only. Not requested as a session of its own: a user
    picks a session to watch (``spectate`` pages), and gets a viewer grant on it."""

    name = "spectate"
    label = "Spectate"
    user_drives = False
    requestable = False
    urls = "kinds.spectate.urls"
    entry_label = "Watch"

    def entry_url(self, service: Service) -> str:
        return reverse("spectate")

    def demo_services(self) -> Mapping[str, DemoService]:
        # Imported here: only the seed reads the demo world.
        from kinds.spectate.demo import demo_services

        return demo_services()
