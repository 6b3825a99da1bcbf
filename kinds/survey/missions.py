"""The mission signed into the surveyor's task, from the recorded state (a re-sent task
carries the same mission, with the same id, and the agent never repeats it)."""

from __future__ import annotations

from agents.missions.spec import MissionSpec
from agents.missions.survey.spec import SurveySpec
from kinds.survey.models import SURVEYOR, Survey
from kinds.survey.planning import plan_lines
from services.models import Assignment

#: Survey speed: slow enough for sharp pictures (and a photo every few metres).
SURVEY_SPEED_MPS = 5.0

#: The missions this kind deploys (:attr:`services.kinds.ServiceKind.missions`).
MISSIONS: tuple[type[MissionSpec], ...] = (SurveySpec,)


def vehicle_mission(*, assignment: Assignment) -> SurveySpec | None:
    """The surveyor's ``survey`` mission (agents/missions/survey/): the planned lines
    from the first photo not taken yet. None for another role or no plan. Raises
    MissionError if the recorded state makes no valid one."""
    survey = Survey.objects.filter(pk=assignment.session_id).first()
    if survey is None or survey.plan is None or assignment.role != SURVEYOR:
        return None
    declared = assignment.vehicle.attributes.get("max_speed_mps")
    speed = min(SURVEY_SPEED_MPS, float(declared)) if declared else SURVEY_SPEED_MPS
    return SurveySpec(
        id=f"{assignment.session_id}-{SURVEYOR}-{assignment.pk}",
        lines=plan_lines(survey.plan),
        spacing_m=survey.plan["spacing_m"],
        altitude_m=survey.plan["altitude_m"],
        speed_mps=speed,
        start_photo=min(survey.next_photo, max(survey.photo_count - 1, 0)),
    )
