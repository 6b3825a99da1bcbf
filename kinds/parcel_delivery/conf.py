"""Parcel delivery's own settings: read from the environment (``iouv.env``), and
overridable in Django's settings under the same name (as tests do)."""

from __future__ import annotations

from django.conf import settings

from iouv.env import env_float, env_int


def parcel_wait_s() -> int:
    """How long a parcel may wait for a vehicle able to take it before the delivery
    fails (``IOUV_PARCEL_WAIT_S``, default 30 min)."""
    configured = getattr(settings, "IOUV_PARCEL_WAIT_S", None)
    if configured is not None:
        return int(configured)
    return env_int("IOUV_PARCEL_WAIT_S", 1800)


def load_s() -> float:
    """How long the carrier waits at the pickup for the parcel to be put on board
    (``IOUV_PARCEL_LOAD_S``, default 15 s)."""
    configured = getattr(settings, "IOUV_PARCEL_LOAD_S", None)
    if configured is not None:
        return float(configured)
    return env_float("IOUV_PARCEL_LOAD_S", 15.0)
