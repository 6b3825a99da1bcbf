"""The operator's fleet monitor, in Chromium against the real platform: the operator
sees the sessions as a monitor does (its feeds are not refused) but cannot stop one,
and the catalog calls them an operator.
"""

from __future__ import annotations

from playwright.async_api import expect

from tests.portal import PORTAL_MARKS, World, request_car

pytestmark = PORTAL_MARKS


async def test_the_operator_watches_the_fleet_and_its_sessions_live(world: World) -> None:
    client = await world.login("client")
    session_id = await request_car(world, client)

    operator = await world.login("operator")
    refused: list[str] = []
    operator.on(
        "console",
        lambda message: refused.append(message.text) if "4403" in message.text else None,
    )
    hint = operator.locator("[data-role-hint]")
    await expect(hint).to_contain_text("As an operator you watch every vehicle")
    await hint.get_by_role("link", name="open the fleet monitor").click()
    await operator.wait_for_url("**/monitor/")
    await expect(operator.locator("[data-conn-state]")).to_have_text("live")
    row = operator.locator(f"[data-session='{session_id}']")
    await expect(row).to_contain_text("Manual control of a car")
    await expect(row).to_contain_text("car-1")
    await expect(operator.locator("[data-no-sessions]")).to_be_hidden()
    # Watching, not stopping: that is the monitors'.
    await expect(row.locator("[data-stop]")).to_have_count(0)
    await expect(operator.locator("[data-fleet] tr[data-vehicle='car-1']")).to_contain_text(
        "in service"
    )
    assert not refused, refused
