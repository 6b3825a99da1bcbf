"""Aerial survey: the state of each survey (one per session)."""

from __future__ import annotations

from django.db import models

from services.models import Session

#: The kind's name (services.kinds), stored in ``Service.kind``.
KIND = "survey"
#: The service role of the drone that flies it.
SURVEYOR = "surveyor"


class Survey(models.Model):
    """An area to photograph from above (one per session): what was asked, the photo
    grid planned for it, how far the flying got, and the mosaic made of the photos; the
    workflow's state machine, kept in the database so any worker takes the next step."""

    class State(models.TextChoices):
        WAITING_VEHICLE = "waiting_vehicle", "waiting for a drone"
        FLYING = "flying", "being photographed"
        PROCESSING = "processing", "photographed; making the mosaic"
        DONE = "done", "mosaic ready"
        CANCELLED = "cancelled"
        FAILED = "failed"

    session = models.OneToOneField(
        Session, on_delete=models.CASCADE, primary_key=True, related_name="survey"
    )
    state = models.CharField(max_length=20, choices=State.choices, default=State.WAITING_VEHICLE)
    #: Why it waits or ended, in words for the user.
    status_text = models.CharField(max_length=300, blank=True)
    #: The area: ``[[lat, lon], ...]``, not closed (the last vertex joins the first).
    polygon = models.JSONField()
    gsd_cm = models.FloatField()
    front_overlap = models.FloatField()
    side_overlap = models.FloatField()
    #: The grid, planned for the first drone's camera and kept for the ones after it:
    #: ``lines``, ``spacing_m``, ``altitude_m``, ``footprint_m``, ``line_spacing_m``.
    plan = models.JSONField(null=True, blank=True)
    photo_count = models.PositiveIntegerField(default=0)
    #: The first photo not taken yet: where the next drone starts.
    next_photo = models.PositiveIntegerField(default=0)
    #: How many drones have flown it (the first, then replacements).
    legs = models.PositiveIntegerField(default=0)
    flown_at = models.DateTimeField(null=True, blank=True)
    #: The mosaic (PNG, north up) and its ``[south, west, north, east]``.
    mosaic = models.BinaryField(null=True, blank=True)
    mosaic_bounds = models.JSONField(null=True, blank=True)
    #: The share of the area the received photos cover.
    coverage = models.FloatField(null=True, blank=True)
    updated_at = models.DateTimeField(auto_now=True)

    def __str__(self) -> str:
        return f"survey {self.session_id} ({self.state})"


#: Survey states after which nothing more happens.
FINAL_SURVEY = frozenset({Survey.State.DONE, Survey.State.CANCELLED, Survey.State.FAILED})
