"""WebSocket consumers of the fleet app."""

from __future__ import annotations

import asyncio
import contextlib
from datetime import datetime
from typing import Any

from channels.db import database_sync_to_async
from channels.generic.websocket import AsyncJsonWebsocketConsumer
from django.conf import settings

from fleet.feed import FLEET_GROUP
from fleet.liveness import in_redis
from fleet.memberships import group_hold, group_release
from operations.consumers import DirectDispatch
from operations.layer import relay_ensure


class FleetFeedConsumer(DirectDispatch, AsyncJsonWebsocketConsumer):
    """Live fleet for monitors: a snapshot on connect, then every change.

    Sends ``{"type": "fleet", "vehicles": [...], "full": bool}``. Users without the
    ``fleet.view_fleet`` permission are refused (close code 4403).

    Changes of state reach it as ``fleet.changed`` (ids; the rows are read here). With
    liveness in Redis, heartbeats no longer touch the rows: every
    ``IOUV_FLEET_FEED_LIVE_S`` the feed reads what the vehicles last reported and
    sends the vehicles heard from since. No monitor, no cost: nothing is pushed per
    heartbeat.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._shown: dict[str, dict[str, Any]] = {}  # id -> the summary last sent
        self._live_task: asyncio.Task[None] | None = None

    async def connect(self) -> None:
        relay_ensure()
        user = self.scope.get("user")
        if user is None or not await database_sync_to_async(user.has_perm)("fleet.view_fleet"):
            await self.close(code=4403)
            return
        await group_hold(FLEET_GROUP, self.channel_name)
        await self.accept()
        await self._send_vehicles(await _snapshot(), full=True)
        if in_redis():
            self._live_task = asyncio.create_task(self._follow_live())

    async def disconnect(self, code: int) -> None:
        if self._live_task is not None:
            self._live_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._live_task
        await group_release(FLEET_GROUP, self.channel_name)

    async def receive_json(self, content: Any, **kwargs: Any) -> None:
        # The feed is read-only; say so rather than silently dropping input.
        await self.send_json({"type": "error", "code": "read_only", "message": "feed is read-only"})

    async def fleet_changed(self, event: dict[str, Any]) -> None:
        await self._send_vehicles(await _snapshot(event["ids"]), full=False)

    async def _send_vehicles(self, vehicles: list[dict[str, Any]], *, full: bool) -> None:
        if full:
            self._shown.clear()
        for vehicle in vehicles:
            self._shown[vehicle["id"]] = vehicle
        await self.send_json({"type": "fleet", "full": full, "vehicles": vehicles})

    async def _follow_live(self) -> None:
        period = float(settings.IOUV_FLEET_FEED_LIVE_S)
        while True:
            await asyncio.sleep(period)
            newer = await _live_since(dict(self._shown))
            if newer:
                await self._send_vehicles(newer, full=False)


@database_sync_to_async
def _snapshot(ids: list[str] | None = None) -> list[dict[str, Any]]:
    from fleet.status import fleet_snapshot

    return fleet_snapshot(ids)


@database_sync_to_async
def _live_since(shown: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The summaries in ``shown`` whose vehicle was heard from since, brought up to date."""
    from fleet.liveness import vehicles_live
    from fleet.status import live_summary

    newer = []
    for pk, live in vehicles_live(shown).items():
        summary = shown[pk]
        last = summary.get("last_seen")
        if last is None or live.seen_at > datetime.fromisoformat(last):
            newer.append({**summary, **live_summary(live)})
    return newer
