"""The survey's own settings: read from the environment (``iouv.env``), and overridable
in Django's settings under the same name (as tests do)."""

from __future__ import annotations

from django.conf import settings

from iouv.env import env_float, env_int


def survey_wait_s() -> int:
    """How long a survey may wait for a drone able to fly it before it fails
    (``IOUV_SURVEY_WAIT_S``, default 30 min)."""
    configured = getattr(settings, "IOUV_SURVEY_WAIT_S", None)
    if configured is not None:
        return int(configured)
    return env_int("IOUV_SURVEY_WAIT_S", 1800)


def photos_wait_s() -> float:
    """How long after the flight the mosaic waits for photos still on their way
    (``IOUV_SURVEY_PHOTOS_WAIT_S``, default 10 min: a drone's uplink may be down)."""
    configured = getattr(settings, "IOUV_SURVEY_PHOTOS_WAIT_S", None)
    if configured is not None:
        return float(configured)
    return env_float("IOUV_SURVEY_PHOTOS_WAIT_S", 600.0)
