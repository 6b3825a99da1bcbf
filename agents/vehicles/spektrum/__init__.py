"""The Spektrum-fed VTOL plane (the paper's 4.2.3): DSMX frames on a serial port; see
``docs/vehicles/vtol.md``.

Files: ``frames`` (the wire format), ``report`` (the return line), ``config`` (options),
``vocabulary`` (commands, telemetry), ``controls`` (the virtual transmitter), ``pump``
(frames out on time), ``adapter`` (pyserial), ``sim/`` (a flight controller on a pty).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import Adapter
from agents.vehicles.registry import Integration
from agents.vehicles.spektrum.vocabulary import spektrum_commands


def _create(options: Mapping[str, Any]) -> Adapter:
    # Imported here: pyserial is loaded only by an agent that flies the plane.
    from agents.vehicles.spektrum.adapter import SpektrumAdapter

    return SpektrumAdapter(options)


INTEGRATION = Integration(
    name="spektrum",
    title="Spektrum receiver (serial)",
    create=_create,
    commands=spektrum_commands,
    simulator="agents.vehicles.spektrum.sim",
)
