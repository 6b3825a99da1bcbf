"""The Raspberry Pi car (the paper's 4.2.1): gpiozero motors, a pan/tilt camera arm and an
HC-SR04 distance sensor; see ``docs/vehicles/car.md``.

Files: ``config`` (options), ``vocabulary`` (commands, telemetry), ``kinematics`` (pose,
dead reckoning), ``adapter`` (gpiozero), ``sim/`` (the simulated world on mock pins).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.vehicles.base import Adapter
from agents.vehicles.car.vocabulary import car_commands
from agents.vehicles.registry import Integration


def _create(options: Mapping[str, Any]) -> Adapter:
    # Imported here: gpiozero is loaded only by an agent that drives a car.
    from agents.vehicles.car.adapter import CarAdapter

    return CarAdapter(options)


INTEGRATION = Integration(
    name="car",
    title="Raspberry Pi car (gpiozero)",
    create=_create,
    commands=car_commands,
    simulator="agents.vehicles.car.sim",
)
