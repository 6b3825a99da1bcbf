"""The table behind the channel-layer relay of embedded mode (see :mod:`operations.layer`):
a worker's group messages wait in ``LayerMessage`` rows until the ASGI process takes
them. Registered with :func:`operations.layer.relay_store_set` when the fleet app is ready."""

from __future__ import annotations

from typing import Any

from django.db import transaction

from fleet.models import LayerMessage


class LayerMessageStore:
    """:class:`operations.layer.RelayStore` on ``fleet.LayerMessage``."""

    def put(self, group: str, message: dict[str, Any]) -> None:
        LayerMessage.objects.create(group=group, message=message)

    def take(self, limit: int) -> list[tuple[str, dict[str, Any]]]:
        with transaction.atomic():
            rows = list(LayerMessage.objects.order_by("pk")[:limit])
            if rows:
                LayerMessage.objects.filter(pk__in=[r.pk for r in rows]).delete()
        return [(r.group, r.message) for r in rows]
