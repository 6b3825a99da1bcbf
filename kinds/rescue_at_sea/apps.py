from django.apps import AppConfig


class RescueAtSeaConfig(AppConfig):
    name = "kinds.rescue_at_sea"
    label = "rescue_at_sea"
    verbose_name = "Rescue at sea"

    def ready(self) -> None:
        from kinds.rescue_at_sea.kind import RescueAtSea
        from services.kit import kind_register

        kind_register(RescueAtSea())
