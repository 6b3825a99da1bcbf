"""MAVLink autopilots (the paper's 4.2.2 quadcopter): the agent is the ground station;
see ``docs/vehicles/quadcopter.md``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import Adapter
from agents.vehicles.mavlink.vocabulary import mavlink_commands
from agents.vehicles.registry import Integration


def _create(options: Mapping[str, Any]) -> Adapter:
    # Imported here: pymavlink is loaded only by an agent that flies an autopilot.
    from agents.vehicles.mavlink.adapter import MavlinkAdapter

    return MavlinkAdapter(options)


INTEGRATION = Integration(
    name="mavlink",
    title="MAVLink autopilot (pymavlink)",
    create=_create,
    commands=mavlink_commands,
    simulator="agents.vehicles.mavlink.sim",
)
