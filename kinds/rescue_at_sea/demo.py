"""The rescue in the demo world: the service, and the coastal station's (fictitious)
lifeguards, whom the demo's rescues alert."""

from __future__ import annotations

from fleet.models import Station, VehicleType
from kinds.rescue_at_sea.models import RescueTeam
from services.kit import COSTA_NOVA, DemoService
from services.models import Service, ServiceRole

K = VehicleType.Kind

#: Fictitious contact details: the demo must never page a real team.
LIFEGUARDS = {
    "name": "Costa Nova lifeguards",
    "email": "lifeguards@costanova.example",
    "phone": "+351 234 000 000",
    "webhook": "",
}


def demo_seed() -> None:
    """The coastal station's rescue team."""
    station = Station.objects.get(name=COSTA_NOVA)
    RescueTeam.objects.update_or_create(station=station, defaults=LIFEGUARDS)


def demo_services() -> dict[str, DemoService]:
    """Person rescue at sea: a thermal-camera searcher, then the nearest capable
    vehicle in the air or on the water brings the life jacket."""
    return {
        "rescue-at-sea": DemoService(
            fields={
                "name": "Person rescue at sea",
                "description": (
                    "Report a person in the water: a thermal-camera drone searches the "
                    "area, then a payload drone or a boat brings a life jacket and the "
                    "rescue team is alerted."
                ),
                "allowed_commands": [],
                "failsafe_action": Service.Failsafe.RETURN_TO_HOME,
                "link_loss_timeout_ms": 500,
                "session_time_limit_s": 1800,
            },
            roles={
                "search": {
                    "kinds": [K.AERIAL, K.HYBRID],
                    "cameras": ["rgb", "thermal"],
                    "environments": ["sea"],
                    "selection": ServiceRole.Selection.FASTEST,
                    "required": True,
                },
                "delivery": {
                    "kinds": [K.AERIAL, K.AQUATIC],
                    "environments": ["sea"],
                    "features": ["payload_release"],
                    "min_attributes": {"max_payload_kg": 1.0},
                    "selection": ServiceRole.Selection.FASTEST,
                    # Assigned by the workflow once the person has been found.
                    "required": False,
                },
            },
        )
    }
