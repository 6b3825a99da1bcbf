"""The Spektrum-fed VTOL plane (the paper's 4.2.3): DSMX frames on a serial port; see
``docs/vehicles/vtol.md``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import Adapter, CommandSpec
from agents.vehicles.registry import Integration


def _create(options: Mapping[str, Any]) -> Adapter:
    # Imported here: pyserial is loaded only by an agent that flies the plane.
    from agents.vehicles.spektrum.adapter import SpektrumAdapter

    return SpektrumAdapter(options)


def _commands(options: Mapping[str, Any]) -> list[CommandSpec]:
    return _create(options).commands()


INTEGRATION = Integration(
    name="spektrum",
    title="Spektrum receiver (serial)",
    create=_create,
    commands=_commands,
    simulator="agents.vehicles.spektrum.sim.simulator",
)
