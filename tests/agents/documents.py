"""The signed documents of the protocol as the tests build them: a task and a grant at a
fixed time (``NOW``), unsigned, for the tests of fields, signing and replay
(test_documents, test_protocol), and the key pairs they are signed with; and a task and
a grant issued now (:func:`task_for`, :func:`grant_for`), which each vehicle's rig
makes with its own vehicle, commands and limits."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from agents.missions.registry import mission_decode
from agents.missions.search.spec import SearchSpec
from agents.missions.spec import MissionSpec
from agents.protocol import (
    Limits,
    UserGrant,
    VehicleTask,
    generate_keypair,
    load_private_key,
    load_public_key,
    new_nonce,
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
        "mission": SearchSpec(
            id="m-1", altitude_m=10, waypoints=((43.7, 7.25), (43.71, 7.26)), speed_mps=2
        ),
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


def task_for(
    vehicle_id: str,
    commands: Sequence[str],
    *,
    session: str = "session-1",
    user: str = "alice",
    ttl: float = 120,
    mission: MissionSpec | dict[str, Any] | None = None,
    **limits: Any,
) -> VehicleTask:
    """``user``'s task on ``vehicle_id`` allowing ``commands``, issued now and ``ttl``
    seconds long, with ``limits`` (the others Limits' defaults) and ``mission`` (a spec,
    or its JSON object, decoded as the agent does: MissionError when malformed)."""
    if isinstance(mission, dict):
        mission = mission_decode(mission)
    now = time.time()
    return VehicleTask(
        session_id=session,
        vehicle_id=vehicle_id,
        user=user,
        allowed_commands=tuple(commands),
        limits=Limits(**limits),
        issued_at=now,
        expires_at=now + ttl,
        nonce=new_nonce(),
        mission=mission,
    )


def grant_for(
    vehicle_id: str,
    commands: Sequence[str],
    key: Any,
    *,
    session: str = "session-1",
    user: str = "alice",
    role: str = "controller",
    ttl: float = 120,
) -> str:
    """``user``'s grant as ``role`` on ``vehicle_id`` allowing ``commands``, ``ttl``
    seconds long (issued a second ago; a negative ``ttl``: one already expired), signed
    with ``key``."""
    now = time.time()
    return UserGrant(
        session_id=session,
        vehicle_id=vehicle_id,
        user=user,
        role=role,
        allowed_commands=tuple(commands),
        issued_at=min(now, now + ttl) - 1,
        expires_at=now + ttl,
        nonce=new_nonce(),
    ).sign(key)
