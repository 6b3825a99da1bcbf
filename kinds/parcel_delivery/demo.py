"""Parcel delivery in the demo world: drones from either station, the boat at sea."""

from __future__ import annotations

from fleet.models import VehicleType
from services.kit import DemoService
from services.models import Service, ServiceRole

K = VehicleType.Kind


def demo_services() -> dict[str, DemoService]:
    """One service: send a parcel between two points."""
    return {
        "parcel-delivery": DemoService(
            fields={
                "name": "Parcel delivery",
                "description": (
                    "Send a parcel: pick the pickup and the drop-off on the map; a drone "
                    "(or the boat, when both are on water) brings it, and the recipient "
                    "follows it with a tracking link."
                ),
                "allowed_commands": [],
                "failsafe_action": Service.Failsafe.RETURN_TO_HOME,
                "link_loss_timeout_ms": 500,
                "session_time_limit_s": 3600,
            },
            roles={
                "carrier": {
                    "kinds": [K.AERIAL, K.AQUATIC],
                    "features": ["payload_release"],
                    "selection": ServiceRole.Selection.FASTEST,
                    # Chosen by the workflow for each parcel, by weight and range.
                    "required": False,
                }
            },
        )
    }
