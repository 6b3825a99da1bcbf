"""The signed documents of the protocol as the tests build them: a task and a grant at a
fixed time (``NOW``), unsigned, for the tests of fields, signing and replay
(test_documents, test_protocol), and the key pairs they are signed with."""

from __future__ import annotations

from typing import Any

from agents.protocol import (
    Limits,
    UserGrant,
    VehicleTask,
    generate_keypair,
    load_private_key,
    load_public_key,
)

NOW = 1_700_000_000.0

PRIVATE_PEM, PUBLIC_PEM = generate_keypair()
PRIVATE = load_private_key(PRIVATE_PEM)
PUBLIC = load_public_key(PUBLIC_PEM)
OTHER_PRIVATE_PEM, OTHER_PUBLIC_PEM = generate_keypair()
OTHER_PRIVATE = load_private_key(OTHER_PRIVATE_PEM)
OTHER_PUBLIC = load_public_key(OTHER_PUBLIC_PEM)


def make_task(**overrides: Any) -> VehicleTask:
    """A task for car-7 issued at ``NOW`` (a minute long, every limit set, a mission);
    ``overrides`` replace its fields."""
    values: dict[str, Any] = {
        "session_id": "s-1",
        "vehicle_id": "car-7",
        "user": "alice",
        "allowed_commands": ("drive", "stop"),
        "limits": Limits(
            max_speed_mps=3.0,
            geofence_center=(43.7, 7.25),
            geofence_radius_m=200.0,
            link_loss_timeout_ms=800,
            latency_soft_ms=150,
            latency_hard_ms=400,
            session_time_limit_s=600,
        ),
        "issued_at": NOW,
        "expires_at": NOW + 60,
        "mission": {"waypoints": [[43.7, 7.25, 10], [43.71, 7.26, 10]]},
    }
    values.update(overrides)
    return VehicleTask(**values)


def make_grant(**overrides: Any) -> UserGrant:
    """alice's controller grant on car-7 issued at ``NOW``, a minute long; ``overrides``
    replace its fields."""
    values: dict[str, Any] = {
        "session_id": "s-1",
        "vehicle_id": "car-7",
        "user": "alice",
        "role": "controller",
        "allowed_commands": ("drive", "stop"),
        "issued_at": NOW,
        "expires_at": NOW + 60,
    }
    values.update(overrides)
    return UserGrant(**values)
