from django.apps import AppConfig


class FleetConfig(AppConfig):
    name = "fleet"
    verbose_name = "Fleet"

    def ready(self) -> None:
        from fleet.layer_relay import LayerMessageStore
        from operations import layer

        layer.relay_store_set(LayerMessageStore())
