"""The vehicle integrations this installation has, by name.

An integration is a package ``agents/vehicles/<name>/`` whose ``__init__.py`` declares
``INTEGRATION = Integration(...)``. Adding one is adding its folder: nothing else names
it (the agent config's ``adapter``, the platform's vehicle types and the demo look it up
here).

An integration's ``__init__.py`` and its vocabulary stay light: no hardware library
(pymavlink, gpiozero, pyserial) is imported before :meth:`Integration.create` makes an
adapter, so the platform can list the integrations and read their command
vocabularies without them.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agents.vehicles.base import Adapter, CommandSpec

#: Where the integrations' folders are.
VEHICLES_DIR = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Integration:
    """What a vehicle integration declares.

    ``create(options)`` makes its adapter (ValueError naming a bad option; importing
    the hardware library happens here, not before). ``commands(options)`` is the
    command vocabulary an adapter made with ``options`` declares, without making one.
    ``simulator`` is the module of its simulator (``simulation(options)``, see
    :class:`~agents.vehicles.base.Simulation`, and ``cli(argv)`` for ``python -m agents
    sim <name>``), or None; only the simulation runner imports it.
    """

    name: str
    title: str
    create: Callable[[Mapping[str, Any]], Adapter]
    commands: Callable[[Mapping[str, Any]], list[CommandSpec]]
    simulator: str | None = None


class UnknownIntegration(KeyError):
    """No integration has this name; the message names the installed ones."""

    def __str__(self) -> str:
        return str(self.args[0])


def integration_names() -> list[str]:
    """The installed integrations: the packages under ``agents/vehicles/``, sorted."""
    return sorted(
        info.name
        for info in pkgutil.iter_modules([str(VEHICLES_DIR)])
        if info.ispkg and not info.name.startswith("_")
    )


def integration(name: str) -> Integration:
    """The integration called ``name``. Raises UnknownIntegration naming the known ones
    (only the folders listed by :func:`integration_names` are ever imported)."""
    names = integration_names()
    if name not in names:
        raise UnknownIntegration(
            f"no vehicle integration {name!r}; installed: {', '.join(names) or 'none'}"
        )
    module = importlib.import_module(f"{__package__}.{name}")
    declared = getattr(module, "INTEGRATION", None)
    if not isinstance(declared, Integration) or declared.name != name:
        raise UnknownIntegration(f"agents/vehicles/{name}/ declares no INTEGRATION named {name!r}")
    return declared


def adapter_create(name: str, options: Mapping[str, Any]) -> Adapter:
    """An adapter of integration ``name`` for ``options`` (not started). Raises
    UnknownIntegration, or ValueError naming a bad option."""
    return integration(name).create(options)
