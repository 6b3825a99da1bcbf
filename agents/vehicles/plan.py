"""A flight plan a vehicle's own mission engine flies: plain waypoints and actions, and
the capability an adapter offers for it (:class:`NativeMissions`).

A mission made only of these (the flight kit builds it, :mod:`agents.missions.plan`)
can be handed to an autopilot that flies missions itself (ArduPilot's AUTO): it then
finishes the mission, or returns home, even if the agent dies. An adapter without such
an engine (the Pi car, the Spektrum VTOL) has none, and the kit flies the same plan
step by step with the vehicle's ordinary commands.

Altitudes are metres above home; positions ``(lat, lon)`` in degrees.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeAlias


@dataclass(frozen=True)
class TakeOff:
    """Climb to ``altitude_m`` where the vehicle is (done at once when higher)."""

    altitude_m: float


@dataclass(frozen=True)
class Waypoint:
    """Fly to ``point`` at ``altitude_m`` and stay ``hold_s`` seconds there."""

    point: tuple[float, float]
    altitude_m: float
    hold_s: float = 0.0


@dataclass(frozen=True)
class Speed:
    """The ground speed of the legs that follow (m/s)."""

    speed_mps: float


@dataclass(frozen=True)
class Release:
    """Release the payload where the vehicle is."""


@dataclass(frozen=True)
class ReturnHome:
    """Return home (a copter lands there, a boat holds)."""


@dataclass(frozen=True)
class Hold:
    """Stay over the last waypoint (where the vehicle is, when there is none) until
    told otherwise: a plan's last item, which the engine never moves past. The vehicle
    hovers or keeps station there, still flying the plan, until someone (the agent, a
    user, a fail-safe) sends it elsewhere."""


PlanItem: TypeAlias = TakeOff | Waypoint | Speed | Release | ReturnHome | Hold


@dataclass(frozen=True)
class MissionProgress:
    """Where the vehicle's engine is in the plan it flies: ``current``, the index of
    the item it is flying (None: not started, or not known yet); ``reached``, the
    highest index of an item it has reached (None: none yet); ``finished``: it has
    flown the whole plan."""

    current: int | None = None
    reached: int | None = None
    finished: bool = False


class NativeMissions(abc.ABC):
    """A vehicle's own mission engine (an autopilot's). The agent serialises these
    calls with the adapter's commands (the control hub's lock)."""

    @abc.abstractmethod
    async def mission_upload(self, items: Sequence[PlanItem]) -> None:
        """Hand ``items`` to the engine, replacing its mission; nothing flies yet. A
        refused or broken upload raises AdapterError naming the refusal and leaves no
        partial mission behind (it is cleared)."""

    @abc.abstractmethod
    async def mission_start(self) -> None:
        """Fly the uploaded mission from its first item. The vehicle must be under way
        already (a copter flying: take off first). Raises AdapterError when refused."""

    @abc.abstractmethod
    async def mission_adopt(self, items: Sequence[PlanItem]) -> bool:
        """Whether the engine flies ``items`` already (the agent started them before it
        restarted): then :meth:`mission_progress` follows that mission from where it is,
        as if :meth:`mission_start` had just started it, and nothing is flown again.
        False, with nothing changed, when it flies nothing or something else. Raises
        AdapterError when the engine cannot be asked."""

    @abc.abstractmethod
    def mission_progress(self) -> MissionProgress:
        """Where the engine is in the uploaded plan. Must not block."""
