"""Simulated vehicles: the one place that starts simulators.

Each vehicle integration's simulator module (named by its
:class:`~agents.vehicles.registry.Integration`) offers a hook, ``simulation(options)``,
that starts the simulator and yields the adapter options that drive the simulated
vehicle (see :class:`~agents.vehicles.base.Simulation`). This module runs those hooks
for ``python -m agents sim`` (a simulated fleet, or one simulator on its own), for tests
and for benchmarks. Production code never imports it, nor any simulator: ``python -m
agents run`` on a vehicle opens the real hardware or fails (the import-linter contracts
in pyproject.toml keep it so).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib
import logging
import sys
from collections.abc import AsyncIterator, Mapping
from types import ModuleType
from typing import Any

from agents.config import AgentConfig
from agents.runtime import Agent, run_until_stopped
from agents.vehicles.base import Adapter, Simulation
from agents.vehicles.registry import UnknownIntegration, adapter_create, integration

log = logging.getLogger(__name__)


def simulator_module(name: str) -> ModuleType:
    """The simulator module of integration ``name``. Raises UnknownIntegration for an
    unknown name, or one without a simulator."""
    module = integration(name).simulator
    if module is None:
        raise UnknownIntegration(f"the {name} integration has no simulator")
    return importlib.import_module(module)


@contextlib.asynccontextmanager
async def simulator_running(name: str, options: Mapping[str, Any]) -> AsyncIterator[Simulation]:
    """Run integration ``name``'s simulator for ``options`` (adapter options, with the
    simulator's own under ``simulator``) until the block ends; yields its
    :class:`Simulation`, whose ``options`` an adapter of ``name`` drives it with."""
    hook = simulator_module(name).simulation
    async with hook(options) as simulation:
        yield simulation


@contextlib.asynccontextmanager
async def adapter_simulated(
    name: str, options: Mapping[str, Any]
) -> AsyncIterator[tuple[Adapter, Simulation]]:
    """A started adapter of ``name`` on its simulator: yields ``(adapter, simulation)``;
    the adapter is closed before the simulator stops."""
    async with (
        simulator_running(name, options) as simulation,
        adapter_create(name, simulation.options) as adapter,
    ):
        yield adapter, simulation


async def agent_simulated_run(config: AgentConfig) -> None:
    """Run one agent on its vehicle's simulator until cancelled."""
    async with simulator_running(config.adapter, config.adapter_options) as simulation:
        await Agent(dataclasses.replace(config, adapter_options=simulation.options)).run()


def fleet_run_forever(configs: list[AgentConfig]) -> None:
    """Run a simulated agent per config in this process until stopped (SIGINT, SIGTERM:
    each vehicle performs its shutdown action, see :func:`run_until_stopped`)."""

    async def main() -> None:
        await asyncio.gather(*(agent_simulated_run(config) for config in configs))

    run_until_stopped(main)


def simulator_cli(name: str, argv: list[str]) -> int:
    """``python -m agents sim <name> ...``: integration ``name``'s simulator on its own
    (its ``cli(argv)``), for ground stations, serial lines and manual tests. Returns the
    exit status (2: no such simulator)."""
    try:
        module = simulator_module(name)
    except UnknownIntegration as exc:
        print(f"no simulator named {name!r}: {exc}", file=sys.stderr)
        return 2
    cli = getattr(module, "cli", None)
    if cli is None:
        print(f"the {name} simulator has no command line: it runs in `sim fleet`", file=sys.stderr)
        return 2
    return int(cli(argv))
