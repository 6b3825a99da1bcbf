"""The ``return`` mission: go home with the session open; see README.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from agents.missions.registry import Mission
from agents.missions.return_home.spec import ReturnSpec

if TYPE_CHECKING:
    from agents.missions.return_home.runner import ReturnRunner


def _runner() -> type[ReturnRunner]:
    from agents.missions.return_home.runner import ReturnRunner

    return ReturnRunner


MISSION = Mission(
    name="return_home", title="Go home with the session open", spec=ReturnSpec, runner=_runner
)
