"""Flies the ``return`` mission: ``returning``, then the vehicle's own
``return_to_home`` (a copter lands there), the session still open."""

from __future__ import annotations

from agents.missions.kit import MissionRunner
from agents.missions.return_home.spec import ReturnSpec


class ReturnRunner(MissionRunner[ReturnSpec]):
    """See the module docstring."""

    async def fly(self) -> None:
        await self.return_home()
