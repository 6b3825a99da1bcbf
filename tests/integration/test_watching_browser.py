"""Watching a session, in Chromium against the real platform: a spectator's page and a
rescue's page that waits for its drone use the platform's sockets only as they may and
need (no refused socket every few seconds, no request for a grant that cannot be there
yet every few seconds), and a spectator sees a monitor's stop end the session."""

from __future__ import annotations

from typing import Any

from django.contrib.auth import get_user_model
from django.utils import timezone
from playwright.async_api import Request, WebSocket, expect

from fleet.models import Vehicle
from kinds.rescue_at_sea.request import rescue_request
from kinds.rescue_at_sea.workflow import mission_advance
from services.demo import CASTAWAY
from services.models import Service, Session
from services.sessions.ending import session_revoke
from tests.portal import PORTAL_MARKS, World, request_car, wait_for
from tests.servers import db

pytestmark = PORTAL_MARKS


def _monitor_stops(session_id: str) -> None:
    session = Session.objects.select_related("service").get(pk=session_id)
    session_revoke(session=session, reason="stopped by a monitor (monitor)", action="stop")


async def test_a_spectator_opens_no_refused_socket_and_sees_a_monitors_stop(
    world: World,
) -> None:
    driver = await world.login("client")
    session_id = await request_car(world, driver)
    spectator = await world.login("client2")
    sockets: list[str] = []
    spectator.on("websocket", lambda ws: sockets.append(ws.url))
    await spectator.goto(f"{world.base}/spectate/{session_id}/")
    await wait_for(spectator, "c.role === 'viewer' && c.stats.framesDecoded > 3")
    await expect(spectator.locator("[data-vehicle-name]")).to_have_text("car-1")
    await expect(spectator.locator("[data-session-state]")).to_have_text("active")

    await db(_monitor_stops, session_id)
    await expect(spectator.locator("[data-banner]")).to_have_text(
        "Session over: stopped by a monitor (monitor)."
    )
    await expect(spectator.locator("[data-session-state]")).not_to_have_text("active")
    # Its sockets: the vehicle's (through the relay), never the session feed it may not
    # open.
    assert not [url for url in sockets if "/ws/sessions/" in url], sockets


def _rescue_waiting() -> Session:
    """search-1 busy elsewhere; the client asks for a rescue near the castaway: it
    waits for its drone."""
    Vehicle.objects.filter(name="search-1").update(
        status=Vehicle.Status.IN_SERVICE, last_seen=timezone.now(), battery=95
    )
    lat, lon = CASTAWAY
    area = [[lat - 0.0005, lon - 0.0008], [lat - 0.0005, lon + 0.0008], [lat + 0.0005, lon]]
    session = rescue_request(
        user=get_user_model().objects.get(username="client"),
        service=Service.objects.get(slug="rescue-at-sea"),
        area=area,
    )
    mission_advance(session.pk)
    return session


def _drone_free(session_id: Any) -> None:
    """search-1 back, idle at its station: the mission's next step assigns it."""
    vehicle = Vehicle.objects.select_related("station").get(name="search-1")
    Vehicle.objects.filter(pk=vehicle.pk).update(
        status=Vehicle.Status.IDLE,
        last_seen=timezone.now(),
        lat=vehicle.station.lat,
        lon=vehicle.station.lon,
    )
    mission_advance(session_id)


async def test_a_waiting_rescue_asks_for_its_grant_once_its_drone_is_assigned(
    world: World,
) -> None:
    session: Any = await db(_rescue_waiting)
    page = await world.login("client")
    grants: list[Request] = []
    page.on("request", lambda r: grants.append(r) if r.url.endswith("/grant") else None)
    feeds: list[WebSocket] = []
    page.on("websocket", lambda ws: feeds.append(ws))
    await page.goto(f"{world.base}/sessions/{session.pk}/")
    await expect(page.locator("[data-mission-status]")).to_contain_text(
        "search-1 is busy with another session"
    )
    # Watched for a while (the old page asked every 1 to 3 s): not one ask.
    await page.wait_for_timeout(6000)
    assert not grants, [r.url for r in grants]
    assert [ws.url for ws in feeds if f"/ws/sessions/{session.pk}/" in ws.url]

    await db(_drone_free, session.pk)
    await page.wait_for_event("requestfinished", lambda r: r.url.endswith("/grant"))
    first = grants[0]
    answer = await first.response()
    assert answer is not None and answer.status == 200
    # Asked once. A later ask is the page connecting again with a fresh grant after this
    # one's vehicle did not answer (no agent runs for search-1 here): on a busy machine it
    # may come before the test looks, but never before this answer.
    answered_at = first.timing["startTime"] + first.timing["responseEnd"]
    assert all(g.timing["startTime"] >= answered_at for g in grants[1:]), [g.timing for g in grants]
