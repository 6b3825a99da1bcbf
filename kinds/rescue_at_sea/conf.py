"""The rescue's own settings: read from the environment (``iouv.env``), and
overridable in Django's settings under the same name (as tests do)."""

from __future__ import annotations

from django.conf import settings

from iouv.env import env_int


def search_timeout_s() -> int:
    """How long a search may last before the mission ends ``timed_out``
    (``IOUV_MISSION_SEARCH_TIMEOUT_S``, default 20 min)."""
    configured = getattr(settings, "IOUV_MISSION_SEARCH_TIMEOUT_S", None)
    if configured is not None:
        return int(configured)
    return env_int("IOUV_MISSION_SEARCH_TIMEOUT_S", 1200)
