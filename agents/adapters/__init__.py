"""Vehicle adapters behind one interface; see :mod:`agents.adapters.base`."""

from agents.adapters.base import (
    REGISTRY,
    Adapter,
    AdapterError,
    Breach,
    CommandSpec,
    Projection,
    VehicleState,
    adapter_class,
    adapter_create,
    register,
)

__all__ = [
    "REGISTRY",
    "Adapter",
    "AdapterError",
    "Breach",
    "CommandSpec",
    "Projection",
    "VehicleState",
    "adapter_class",
    "adapter_create",
    "register",
]
