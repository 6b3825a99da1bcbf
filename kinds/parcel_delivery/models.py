"""Parcel delivery: the state of each delivery."""

from __future__ import annotations

import secrets

from django.db import models

from services.models import Session

#: The kind's name (services.kinds), stored in ``Service.kind``.
KIND = "parcel_delivery"
#: The service role of the vehicle that carries the parcel.
CARRIER = "carrier"


def _tracking_token() -> str:
    return secrets.token_urlsafe(18)


class Delivery(models.Model):
    """One parcel from a pickup to a drop-off point (one per session): the workflow's
    state machine, kept in the database so any worker can take the next step."""

    class State(models.TextChoices):
        WAITING_CARRIER = "waiting_carrier", "waiting for a vehicle"
        TO_PICKUP = "to_pickup", "on its way to the pickup"
        TO_DROPOFF = "to_dropoff", "parcel on board, on its way to the drop-off"
        RETURNING = "returning", "delivered; the vehicle is returning"
        DELIVERED = "delivered"
        CANCELLED = "cancelled"
        FAILED = "failed"

    session = models.OneToOneField(
        Session, on_delete=models.CASCADE, primary_key=True, related_name="delivery"
    )
    state = models.CharField(max_length=20, choices=State.choices, default=State.WAITING_CARRIER)
    #: Why it waits or ended, in words for the user, the recipient and monitors.
    status_text = models.CharField(max_length=300, blank=True)
    pickup_lat = models.FloatField()
    pickup_lon = models.FloatField()
    dropoff_lat = models.FloatField()
    dropoff_lon = models.FloatField()
    weight_kg = models.FloatField()
    #: Both points on water: a boat may carry it (else only aircraft).
    over_water = models.BooleanField(default=False)
    recipient_name = models.CharField(max_length=100, blank=True)
    recipient_email = models.EmailField(blank=True)
    recipient_webhook = models.URLField(blank=True)
    #: Opens the recipient's tracking page without an account.
    tracking_token = models.CharField(max_length=40, unique=True, default=_tracking_token)
    #: Where the parcel waits when its carrier had to give up with it on board (it is
    #: picked up there by the next one); null: at the pickup, or on board.
    handover_lat = models.FloatField(null=True, blank=True)
    handover_lon = models.FloatField(null=True, blank=True)
    loaded_at = models.DateTimeField(null=True, blank=True)
    released_at = models.DateTimeField(null=True, blank=True)
    #: How many vehicles have carried it (the first, then replacements).
    legs = models.PositiveIntegerField(default=0)
    updated_at = models.DateTimeField(auto_now=True)

    def __str__(self) -> str:
        return f"delivery {self.session_id} ({self.state})"

    @property
    def pickup(self) -> tuple[float, float]:
        """Where the next carrier collects the parcel (a handover point, if any)."""
        if self.handover_lat is not None and self.handover_lon is not None:
            return (self.handover_lat, self.handover_lon)
        return (self.pickup_lat, self.pickup_lon)

    @property
    def dropoff(self) -> tuple[float, float]:
        return (self.dropoff_lat, self.dropoff_lon)

    def pickup_lat_lon(self) -> tuple[float, float]:
        """The pickup the user asked for (the parcel may since wait elsewhere)."""
        return (self.pickup_lat, self.pickup_lon)


#: Delivery states after which nothing more happens.
FINAL_DELIVERY = frozenset(
    {Delivery.State.DELIVERED, Delivery.State.CANCELLED, Delivery.State.FAILED}
)
