"""The ``return`` mission's spec: go home with the session still open."""

from __future__ import annotations

from agents.missions.spec import MissionSpec


class ReturnSpec(MissionSpec, frozen=True, kw_only=True, tag="return"):
    """Go home (the vehicle's ``return_to_home``) while the session stays open: its
    users watch the way back (a rescue's last phase)."""
