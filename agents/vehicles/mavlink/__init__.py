"""MAVLink autopilots: the agent is the vehicle's ground station. One integration for
the vehicle classes ArduPilot flies and drives (:mod:`.classes`): the copter (the
paper's 4.2.2 quadcopter, ``docs/vehicles/quadcopter.md``), the rover and the boat
(ArduRover, ``docs/vehicles/boat.md``); the ``vehicle_class`` option says which.

Files: ``classes`` (each class's modes), ``config`` (options), ``vocabulary`` (commands,
telemetry), ``dialect`` (pymavlink, the wire's constants), ``link`` (the port, threads,
acknowledged commands, parameters), ``failsafe`` (the autopilot's own fail-safe
against a task), ``adapter`` (what the classes share), ``copter`` and ``rover`` (what
they do not), ``sim/`` (an ArduPilot-like autopilot in a process of its own).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import Adapter
from agents.vehicles.mavlink.config import MavlinkConfig
from agents.vehicles.mavlink.vocabulary import mavlink_commands
from agents.vehicles.registry import Integration


def mavlink_adapter_create(options: Mapping[str, Any]) -> Adapter:
    """The adapter of the vehicle class the options name (ValueError on a bad option)."""
    # Imported here: pymavlink is loaded only by an agent that drives an autopilot.
    if MavlinkConfig.from_options(options).vehicle_class.flies:
        from agents.vehicles.mavlink.copter import CopterAdapter

        return CopterAdapter(options)
    from agents.vehicles.mavlink.rover import RoverAdapter

    return RoverAdapter(options)


INTEGRATION = Integration(
    name="mavlink",
    title="MAVLink autopilot: copter, rover or boat (pymavlink)",
    create=mavlink_adapter_create,
    commands=mavlink_commands,
    simulator="agents.vehicles.mavlink.sim",
)
