from django.apps import AppConfig


class SurveyConfig(AppConfig):
    name = "kinds.survey"
    label = "survey"
    verbose_name = "Aerial survey"

    def ready(self) -> None:
        from kinds.survey.kind import AerialSurvey
        from services.kit import kind_register

        kind_register(AerialSurvey())
