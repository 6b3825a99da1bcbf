"""The aerial survey in the demo world: the campus drone with its survey camera."""

from __future__ import annotations

from fleet.models import VehicleType
from services.kit import DemoService
from services.models import Service, ServiceRole


def demo_services() -> dict[str, DemoService]:
    """One service: photograph an area and get its mosaic."""
    return {
        "aerial-survey": DemoService(
            fields={
                "name": "Aerial survey",
                "description": (
                    "Draw an area on the map and pick a ground resolution: a drone with "
                    "a survey camera photographs it line by line, you watch the photos "
                    "cover it, and get a mosaic to overlay on the map or open in a GIS."
                ),
                "allowed_commands": [],
                "failsafe_action": Service.Failsafe.RETURN_TO_HOME,
                "link_loss_timeout_ms": 500,
                "session_time_limit_s": 3600,
                "max_altitude_m": 120,
            },
            roles={
                "surveyor": {
                    "kinds": [VehicleType.Kind.AERIAL],
                    "cameras": ["rgb"],
                    "selection": ServiceRole.Selection.FASTEST,
                    # Chosen by the workflow for each survey, by camera and range.
                    "required": False,
                }
            },
        )
    }
