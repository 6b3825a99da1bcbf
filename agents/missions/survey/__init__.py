"""The ``survey`` mission: photograph an area from a grid of lines; see README.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from agents.missions.registry import Mission
from agents.missions.survey.spec import SurveySpec

if TYPE_CHECKING:
    from agents.missions.survey.runner import SurveyRunner


def _runner() -> type[SurveyRunner]:
    from agents.missions.survey.runner import SurveyRunner

    return SurveyRunner


MISSION = Mission(
    name="survey",
    title="Photograph an area straight down from a grid of lines",
    spec=SurveySpec,
    runner=_runner,
)
