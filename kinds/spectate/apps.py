from django.apps import AppConfig


class SpectateConfig(AppConfig):
    name = "kinds.spectate"
    label = "spectate"
    verbose_name = "Spectate"

    def ready(self) -> None:
        from kinds.spectate.kind import Spectate
        from services.kit import kind_register

        kind_register(Spectate())
