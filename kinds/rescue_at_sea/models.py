"""Rescue at sea: the mission of each rescue."""

from __future__ import annotations

from django.db import models

from fleet.models import Station
from services.models import Session


class RescueTeam(models.Model):
    """The people a station's rescues call when the person is found: the dashboard
    always, and this team by e-mail and webhook where it has them."""

    station = models.OneToOneField(
        Station, on_delete=models.CASCADE, primary_key=True, related_name="rescue_team"
    )
    name = models.CharField(max_length=100, blank=True)
    email = models.EmailField(blank=True)
    phone = models.CharField(max_length=40, blank=True)
    #: Receives a JSON POST per person found (see docs/rescue.md).
    webhook = models.URLField(blank=True)

    def __str__(self) -> str:
        return self.name or f"rescue team of {self.station}"


class Mission(models.Model):
    """The state of one rescue (one per session): the workflow's state machine.

    The state machine lives here, in the database, so any worker can take the next
    step and a killed worker loses nothing; every change is also in the session log.
    """

    class State(models.TextChoices):
        WAITING_SEARCH = "waiting_search", "waiting for a search vehicle"
        SEARCHING = "searching"
        WAITING_DELIVERY = "waiting_delivery", "person found, waiting for a delivery vehicle"
        DELIVERING = "delivering"
        RETURNING = "returning", "vehicles returning to their stations"
        COMPLETED = "completed"
        NOT_FOUND = "not_found", "search finished without finding the person"
        TIMED_OUT = "timed_out", "search timed out"
        FAILED = "failed"
        ABORTED = "aborted"

    session = models.OneToOneField(
        Session, on_delete=models.CASCADE, primary_key=True, related_name="mission"
    )
    state = models.CharField(max_length=20, choices=State.choices, default=State.WAITING_SEARCH)
    #: Why the mission waits or ended, in words for the user and monitors.
    status_text = models.CharField(max_length=300, blank=True)
    #: The search area: [[lat, lon], ...], a simple polygon.
    area = models.JSONField()
    altitude_m = models.FloatField()
    speed_mps = models.FloatField()
    spacing_m = models.FloatField(default=0.0)
    #: The coverage path: [[lat, lon], ...] in flying order.
    path = models.JSONField(default=list, blank=True)
    #: Index in ``path`` of the last waypoint a search vehicle reached (-1: none yet).
    progress = models.IntegerField(default=-1)
    #: {"lat", "lon", "confidence", ...} once the person is found.
    detection = models.JSONField(null=True, blank=True)
    detected_at = models.DateTimeField(null=True, blank=True)
    released_at = models.DateTimeField(null=True, blank=True)
    search_deadline = models.DateTimeField(null=True, blank=True)
    #: How many search vehicles have flown it (the first, then replacements).
    search_legs = models.PositiveIntegerField(default=0)
    updated_at = models.DateTimeField(auto_now=True)

    class Meta:
        # Created by the services app before rescue became a kind of its own.
        db_table = "services_mission"

    def __str__(self) -> str:
        return f"mission {self.session_id} ({self.state})"


#: The kind's name (services.kinds), stored in ``Service.kind``.
KIND = "rescue_at_sea"

#: The service roles of a rescue: the drone that searches, the vehicle that delivers.
SEARCH = "search"
DELIVERY = "delivery"

#: Mission states after which nothing more happens.
FINAL_MISSION = frozenset(
    {
        Mission.State.COMPLETED,
        Mission.State.NOT_FOUND,
        Mission.State.TIMED_OUT,
        Mission.State.FAILED,
        Mission.State.ABORTED,
    }
)
#: Mission states in which vehicles are still out working.
WORKING = frozenset(
    {
        Mission.State.WAITING_SEARCH,
        Mission.State.SEARCHING,
        Mission.State.WAITING_DELIVERY,
        Mission.State.DELIVERING,
    }
)
