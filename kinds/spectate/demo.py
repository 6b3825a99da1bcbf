"""Spectating in the demo world: watch any vehicle with a camera."""

from __future__ import annotations

from services.kit import DemoService
from services.models import Service


def demo_services() -> dict[str, DemoService]:
    """One service: watch a live session's vehicle."""
    return {
        "spectate": DemoService(
            fields={
                "name": "Spectate a vehicle",
                "description": "Watch a vehicle's camera; no control.",
                # View only: spectating grants the viewer role, never control.
                "allowed_commands": [],
                "failsafe_action": Service.Failsafe.STOP,
                "link_loss_timeout_ms": 500,
                "session_time_limit_s": 600,
            },
            roles={"vehicle": {"cameras": ["rgb"], "min_battery": 0}},
        )
    }
