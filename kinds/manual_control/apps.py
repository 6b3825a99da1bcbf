from django.apps import AppConfig


class ManualControlConfig(AppConfig):
    name = "kinds.manual_control"
    label = "manual_control"
    verbose_name = "Manual control"

    def ready(self) -> None:
        from kinds.manual_control.kind import ManualControl
        from services.kit import kind_register

        kind_register(ManualControl())
