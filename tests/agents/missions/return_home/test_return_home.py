"""The ``return`` mission (agents/missions/return_home/) on the MAVLink simulator: the
last leg of a rescue, home with the session still open."""

from __future__ import annotations

from agents.missions.registry import mission_decode
from agents.missions.return_home.spec import ReturnSpec
from tests.agents.mission_rig import HOME, RigFactory, delivery, make_task, until_near
from tests.agents.waiting import until


def test_return_is_its_kind_and_an_id() -> None:
    spec = mission_decode({"kind": "return", "id": "s-1-search-1-home"})
    assert spec == ReturnSpec(id="s-1-search-1-home")
    assert spec.to_payload() == {"kind": "return", "id": "s-1-search-1-home"}


async def test_a_flying_drone_sent_home_returns_with_the_session_open(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(delivery()))
    await rig.event("mission_progress", 30, count=2)  # took off, on its way
    rig.accept(make_task({"kind": "return", "id": "m-home"}))
    progress = await rig.event("mission_progress", 10, count=3)
    assert progress["mission"] == "m-home" and progress["phase"] == "returning"
    # The autopilot flies it home itself (RTL) and lands: waited for as a state, since
    # a drone still climbing over its station is near home before it is told anything.
    await until(lambda: rig.drone.state().mode in ("RTL", "LAND"), within=30, what="RTL or LAND")
    await until_near(rig.drone, HOME, 3.0, within=60)
    # Its session is still the vehicle's task: the user watches the way back.
    assert rig.hub.task is not None and rig.hub.task.session_id == "s-1"
    assert not rig.events("mission_failed") and not rig.events("payload_released")
    # The replaced delivery stopped without a word.
    assert [d["phase"] for _, d in rig.events("mission_progress")] == [
        "takeoff",
        "transit",
        "returning",
    ]
