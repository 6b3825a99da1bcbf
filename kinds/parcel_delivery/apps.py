from django.apps import AppConfig


class ParcelDeliveryConfig(AppConfig):
    name = "kinds.parcel_delivery"
    label = "parcel_delivery"
    verbose_name = "Parcel delivery"

    def ready(self) -> None:
        from kinds.parcel_delivery.kind import ParcelDelivery
        from services.kit import kind_register

        kind_register(ParcelDelivery())
