"""Telling the parcel's recipient: on its way (with the tracking link), delivered.
The core's notices deliver it once per channel (services.sessions.notices)."""

from __future__ import annotations

from django.conf import settings
from django.urls import reverse

from kinds.parcel_delivery.models import Delivery
from services.kit import notice_create
from services.models import Notice

#: The notices' topics, by moment.
TOPICS = {"dispatched": "parcel_dispatched", "delivered": "parcel_delivered"}


def tracking_url(delivery: Delivery) -> str:
    """The recipient's page for this parcel (no account needed: the link is the key)."""
    path = reverse("parcel_track", args=[delivery.tracking_token])
    return f"{settings.IOUV_PUBLIC_URL.rstrip('/')}{path}"


def parcel_notices(delivery: Delivery, *, moment: str) -> None:
    """Owe the recipient a notice of ``moment`` (``dispatched`` or ``delivered``) on
    every channel they gave; a moment is told once."""
    link = tracking_url(delivery)
    dropoff = f"{delivery.dropoff_lat:.5f}, {delivery.dropoff_lon:.5f}"
    sender = delivery.session.user.get_username()
    if moment == "dispatched":
        subject = "[IoUV] A parcel is on its way to you"
        text = f"A parcel from {sender} is on its way to {dropoff}. Follow it live: {link}"
    else:
        subject = "[IoUV] Your parcel was delivered"
        text = f"The parcel from {sender} was delivered at {dropoff}. Details: {link}"
    payload = {
        "event": TOPICS[moment],
        "delivery": str(delivery.pk),
        "lat": delivery.dropoff_lat,
        "lon": delivery.dropoff_lon,
        "tracking_url": link,
    }
    greeting = f"Hello {delivery.recipient_name},\n\n" if delivery.recipient_name else ""
    channels = []
    if delivery.recipient_email:
        channels.append((Notice.Channel.EMAIL, delivery.recipient_email))
    if delivery.recipient_webhook:
        channels.append((Notice.Channel.WEBHOOK, delivery.recipient_webhook))
    for channel, target in channels:
        notice_create(
            session=delivery.session,
            channel=channel,
            topic=TOPICS[moment],
            target=target,
            subject=subject,
            message=f"{greeting}{text}\n" if channel == Notice.Channel.EMAIL else text,
            payload=payload,
        )
