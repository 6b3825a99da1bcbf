"""WebSocket consumers of the fleet app."""

from __future__ import annotations

from typing import Any

from channels.db import database_sync_to_async
from channels.generic.websocket import AsyncJsonWebsocketConsumer

from fleet.feed import FLEET_GROUP
from iouv.consumers import DirectDispatch
from iouv.layer import relay_ensure


class FleetFeedConsumer(DirectDispatch, AsyncJsonWebsocketConsumer):
    """Live fleet for monitors: a snapshot on connect, then every change.

    Sends ``{"type": "fleet", "vehicles": [...], "full": bool}``. Users without the
    ``fleet.view_fleet`` permission are refused (close code 4403).
    """

    async def connect(self) -> None:
        relay_ensure()
        user = self.scope.get("user")
        if user is None or not await database_sync_to_async(user.has_perm)("fleet.view_fleet"):
            await self.close(code=4403)
            return
        await self.channel_layer.group_add(FLEET_GROUP, self.channel_name)
        await self.accept()
        await self.send_json({"type": "fleet", "full": True, "vehicles": await _snapshot()})

    async def disconnect(self, code: int) -> None:
        await self.channel_layer.group_discard(FLEET_GROUP, self.channel_name)

    async def receive_json(self, content: Any, **kwargs: Any) -> None:
        # The feed is read-only; say so rather than silently dropping input.
        await self.send_json({"type": "error", "code": "read_only", "message": "feed is read-only"})

    async def fleet_changed(self, event: dict[str, Any]) -> None:
        await self.send_json(
            {"type": "fleet", "full": False, "vehicles": await _snapshot(event["ids"])}
        )


@database_sync_to_async
def _snapshot(ids: list[str] | None = None) -> list[dict[str, Any]]:
    from fleet.status import fleet_snapshot

    return fleet_snapshot(ids)
