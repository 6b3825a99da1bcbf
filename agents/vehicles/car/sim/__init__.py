"""The car's simulator: a kinematic world behind gpiozero mock pins.

:func:`simulation` is the integration's simulator hook (see
:class:`~agents.vehicles.base.Simulation`): it builds a per-car gpiozero ``MockFactory``
whose pins a :class:`~agents.vehicles.car.sim.world.CarWorld` reads (motors) and drives
(the distance sensor's echo), starts the world, and yields the adapter options with the
factory as ``pin_factory`` and the world as ``sensors``: the adapter then opens exactly
the devices it opens on a Pi. Only :mod:`agents.simulation` and tests import this.

The simulator's parameters (the ``simulator`` option, all optional):

``obstacles``                  ``[{"circle": [north, east, radius]}, {"box": [north,
                               east, size_north, size_east]}]``, metres from the origin
``body_radius_m``              the car's round body (0.12)
``battery_pct``                the charge it starts with (100)
``battery_drain_pct_per_s``    the drain at full power on both motors (0.05)
``hz``                         physics steps per second (50); 0: nothing steps the
                               world but the caller (deterministic tests)
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Mapping
from typing import Any

from gpiozero.pins.mock import (  # type: ignore[import-untyped, unused-ignore]
    MockFactory,
    MockPWMPin,
)

from agents.vehicles.base import Simulation
from agents.vehicles.car.config import CarConfig
from agents.vehicles.car.kinematics import Pose
from agents.vehicles.car.sim.world import CarWorld, obstacles_from_spec
from agents.vehicles.kit import OptionReader, simulator_split

#: Where a simulated car starts when the options give no ``origin``: an arbitrary
#: point (Leiria, Portugal).
SIM_ORIGIN = (39.7436, -8.8071)


@contextlib.asynccontextmanager
async def simulation(options: Mapping[str, Any]) -> AsyncIterator[Simulation]:
    """Start a simulated car for ``options`` (see the module docstring); yields the
    adapter options that drive it and the :class:`CarWorld` as ``simulator``. Raises
    ValueError naming a bad option before anything starts."""
    adapter_options, params = simulator_split(options)
    config = CarConfig.from_options(adapter_options)
    o = OptionReader("car", params, prefix="simulator.")
    obstacles = o.get("obstacles", [])
    try:
        built = obstacles_from_spec(obstacles)
    except (TypeError, ValueError) as exc:
        raise o.error("obstacles", str(exc)) from None
    body_radius_m = o.number("body_radius_m", 0.12, above=0)
    battery_pct = o.number("battery_pct", 100.0, min=0, max=100)
    drain = o.number("battery_drain_pct_per_s", 0.05, min=0)
    hz = o.number("hz", 50.0, min=0)
    o.finish()

    # One factory per car: its pins and reservations are its own, so several simulated
    # cars can share a process (gpiozero's global factory is untouched).
    factory = MockFactory(pin_class=MockPWMPin)
    world = CarWorld(
        factory,
        left=config.left,
        right=config.right,
        origin=config.origin or SIM_ORIGIN,
        pose=Pose(heading_deg=config.heading_deg),
        max_speed_mps=config.max_speed_mps,
        track_width_m=config.track_width_m,
        body_radius_m=body_radius_m,
        battery_pct=battery_pct,
        battery_drain_pct_per_s=drain,
        sensor_max_range_m=config.distance_max_m,
        obstacles=built,
    )
    if config.distance_sensor:
        world.attach_distance_sensor(config.distance_trigger_pin, config.distance_echo_pin)
    task = asyncio.create_task(world.run(hz), name="car-world") if hz > 0 else None
    try:
        yield Simulation(
            options={**adapter_options, "pin_factory": factory, "sensors": world},
            simulator=world,
        )
    finally:
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        with contextlib.suppress(Exception):
            factory.close()
