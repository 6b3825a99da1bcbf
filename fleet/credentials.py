"""Vehicle credentials: issued once, stored as a digest, checked on the uplink.

A credential is 32 random bytes, so unlike a password it cannot be guessed from a
dictionary; a single SHA-256 is then as strong as a slow password hash and keeps a
thousand agents reconnecting at once cheap for the platform.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import uuid

from django.db import transaction
from django.db.models import F
from django.utils import timezone

from fleet.models import Vehicle
from fleet.outbox import vehicle_disconnect_older_uplinks


def _digest(credential: str) -> str:
    return hashlib.sha256(credential.encode()).hexdigest()


def vehicle_issue_credential(*, vehicle: Vehicle) -> str:
    """Make a fresh credential for ``vehicle``, store its digest and return it.

    The plain value is returned only here: show it once and put it in the agent's
    config. Any earlier credential stops working, and an uplink authenticated with one
    is closed wherever it is (fleet.outbox), within a second.
    """
    credential = secrets.token_urlsafe(32)
    with transaction.atomic():
        locked = Vehicle.objects.select_for_update().get(pk=vehicle.pk)
        Vehicle.objects.filter(pk=vehicle.pk).update(
            credential_hash=_digest(credential),
            credential_issued_at=timezone.now(),
            credential_generation=F("credential_generation") + 1,
        )
        generation = locked.credential_generation + 1
        if locked.credential_hash:
            vehicle_disconnect_older_uplinks(vehicle_id=vehicle.pk, generation=generation)
    vehicle.credential_hash = _digest(credential)
    vehicle.credential_generation = generation
    return credential


def vehicle_authenticate(*, vehicle_id: str, credential: str) -> Vehicle | None:
    """The vehicle whose id and credential match, else None (never raises on bad input)."""
    try:
        pk = uuid.UUID(str(vehicle_id))
    except ValueError:
        return None
    vehicle = Vehicle.objects.select_related("vehicle_type", "station").filter(pk=pk).first()
    if vehicle is None or not vehicle.credential_hash or not isinstance(credential, str):
        return None
    if not hmac.compare_digest(vehicle.credential_hash, _digest(credential)):
        return None
    return vehicle
