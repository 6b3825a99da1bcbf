"""The ``parcel`` mission (agents/missions/parcel/) flown on the MAVLink simulator: collect a
parcel at the pickup, bring it to the drop-off, release it once, go home."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

import pytest

from agents.geo import distance_m, offset
from agents.geography import land_at
from agents.missions.parcel.spec import ParcelSpec
from agents.missions.registry import mission_decode
from agents.missions.spec import MissionError
from tests.agents.mission_rig import HOME, RigFactory, make_task, releases

PICKUP = offset(HOME, 30, 0)
DROPOFF = offset(HOME, 30, 60)


def parcel(mission_id: str = "m-parcel", **overrides: Any) -> dict[str, Any]:
    return {
        "kind": "parcel",
        "id": mission_id,
        "pickup": list(PICKUP),
        "dropoff": list(DROPOFF),
        "altitude_m": 15,
        "load_altitude_m": 2,
        "load_s": 1,
        "drop_altitude_m": 3,
        "speed_mps": 8,
        **overrides,
    }


async def until(done: Callable[[], bool], *, within: float) -> None:
    deadline = time.monotonic() + within
    while not done():
        assert time.monotonic() < deadline, "not reached in time"
        await asyncio.sleep(0.05)


def test_a_parcel_mission_is_validated() -> None:
    mission = mission_decode(parcel())
    assert isinstance(mission, ParcelSpec) and mission.pickup == PICKUP
    assert mission.to_payload() == parcel()  # as it travels
    with pytest.raises(MissionError, match="dropoff"):
        mission_decode(parcel(dropoff=[95, 0]))
    with pytest.raises(MissionError, match="above altitude_m"):
        mission_decode(parcel(drop_altitude_m=20))
    with pytest.raises(MissionError, match="load_s"):
        mission_decode(parcel(load_s=-1))
    with pytest.raises(MissionError, match="unknown field"):
        mission_decode(parcel(colour="red"))
    with pytest.raises(MissionError, match="load_altitude_m"):
        mission_decode(parcel(load_altitude_m=None))
    defaults = mission_decode(
        {"kind": "parcel", "id": "p", "pickup": PICKUP, "dropoff": DROPOFF, "altitude_m": 20}
    )
    assert isinstance(defaults, ParcelSpec)
    assert (defaults.load_altitude_m, defaults.load_s, defaults.drop_altitude_m) == (2.0, 10.0, 3.0)
    assert defaults.speed_mps == 10.0


async def test_the_drone_collects_brings_releases_once_and_goes_home(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(parcel()))
    loaded = await rig.event("parcel_loaded", within=90)
    assert distance_m((loaded["lat"], loaded["lon"]), PICKUP) < 5
    assert loaded["alt"] < 4  # it came down to have it put on board
    released = await rig.event("payload_released", within=90)
    assert distance_m((released["lat"], released["lon"]), DROPOFF) < 5
    assert releases(rig.drone) == 1
    phases = [phase for phase, _ in rig.progress()]
    assert phases[:1] == ["takeoff"]
    assert [p for p in phases if p != "takeoff"][:4] == [
        "to_pickup",
        "loading",
        "to_dropoff",
        "delivery",
    ]
    await until(lambda: "returning" in [p for p, _ in rig.progress()], within=30)
    await until(lambda: rig.drone.state().mode == "RTL", within=30)  # on its way home
    # The same task again (a resend): nothing is flown or released again.
    rig.accept(make_task(parcel()))
    assert releases(rig.drone) == 1
    assert [e for e, _ in rig.events()].count("payload_released") == 2  # told, not redone


#: A boat at sea off Barra beach (the demo's Costa Nova station is 720 m east); the
#: pickup, the drop-off and the way between them are water.
BOAT_HOME = (40.6443, -8.7540)
BOAT_PICKUP = offset(BOAT_HOME, 60, 0)
BOAT_DROPOFF = offset(BOAT_HOME, 60, 80)


async def test_a_boat_sails_the_parcel_mission_on_the_water(
    make_mission_rig: RigFactory,
) -> None:
    """No take-off, no descents: the boat is armed, sails to the pickup, waits to be
    loaded there, sails to the drop-off, releases once, and goes home, where it holds."""
    rig = await make_mission_rig(
        vehicle_class="boat", origin=list(BOAT_HOME), simulator={"speedup": 6}
    )
    assert all(land_at(*p) is False for p in (BOAT_HOME, BOAT_PICKUP, BOAT_DROPOFF))
    assert rig.drone.state().armed is False
    rig.accept(make_task(parcel("m-boat", pickup=list(BOAT_PICKUP), dropoff=list(BOAT_DROPOFF))))
    loaded = await rig.event("parcel_loaded", within=60)
    assert distance_m((loaded["lat"], loaded["lon"]), BOAT_PICKUP) < 5
    assert loaded["alt"] is None  # on the surface: nothing to come down from
    released = await rig.event("payload_released", within=60)
    assert distance_m((released["lat"], released["lon"]), BOAT_DROPOFF) < 5
    assert releases(rig.drone) == 1
    phases = [phase for phase, _ in rig.progress()]
    assert phases == ["to_pickup", "loading", "to_dropoff", "delivery", "returning"]

    def home_and_holding() -> bool:
        st = rig.drone.state()
        return (
            st.position is not None
            and distance_m(st.position, BOAT_HOME) < 4
            and (st.speed_mps or 0) < 0.2
        )

    await until(home_and_holding, within=60)
    st = rig.drone.state()
    assert st.mode == "RTL" and st.armed is True  # a boat holds at home, it does not land
    assert not rig.events("mission_failed")
