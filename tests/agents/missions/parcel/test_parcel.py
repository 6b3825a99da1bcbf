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
from agents.vehicles.mavlink.dialect import MAV, mavutil
from agents.vehicles.plan import MissionProgress
from tests.agents.mission_rig import (
    HOME,
    SIM,
    Rig,
    RigFactory,
    agent_dies,
    landed_at_home,
    last_position,
    listen,
    make_task,
    releases,
    texts,
)

AUTO, RTL = 3, 6
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
    with pytest.raises(MissionError, match=r"mission\.colour: is not known"):
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
    """A copter's autopilot flies the whole mission itself (AUTO): the agent follows it
    and reports the same phases and events as when it flies each step."""
    rig = await make_mission_rig()
    rig.accept(make_task(parcel()))
    loaded = await rig.event("parcel_loaded", within=90)
    assert distance_m((loaded["lat"], loaded["lon"]), PICKUP) < 5
    assert loaded["alt"] < 4  # it came down to have it put on board
    released = await rig.event("payload_released", within=90)
    assert distance_m((released["lat"], released["lon"]), DROPOFF) < 5
    await until(lambda: "returning" in [p for p, _ in rig.progress()], within=30)
    assert releases(rig.drone) == 1
    assert [phase for phase, _ in rig.progress()] == [
        "takeoff", "to_pickup", "loading", "to_dropoff", "delivery", "returning",
    ]  # fmt: skip
    assert rig.drone.state().mode == "AUTO"  # the autopilot's own mission, not a command
    assert not rig.events("native_mission_refused")
    # The same task again (a resend): nothing is flown or released again.
    rig.accept(make_task(parcel()))
    assert releases(rig.drone) == 1
    assert [e for e, _ in rig.events()].count("payload_released") == 2  # told, not redone
    # The mission's last item: home, where the autopilot lands and disarms by itself.
    await until(lambda: rig.drone.state().armed is False, within=60)
    assert distance_m(rig.drone.state().position or (0, 0), HOME) < 3
    assert rig.drone.mission_progress().finished
    # A second parcel: a new plan replaces the finished one, whose last word (complete,
    # at its last item) must not pass for the new one's.
    accepted_at = time.monotonic()
    rig.accept(make_task(parcel("m-parcel-2")))
    await until(lambda: rig.drone.state().mode == "AUTO", within=60)
    assert [e for e, _ in rig.events()].count("payload_released") == 2  # not yet
    second = await rig.event("parcel_loaded", within=90, count=2)
    assert distance_m((second["lat"], second["lon"]), PICKUP) < 5 and second["alt"] < 4
    await rig.event("payload_released", within=90, count=3)
    assert any(
        at > accepted_at and text == "Gripper load released" for at, _, text in rig.drone.texts
    )  # the autopilot released the second parcel
    assert not rig.events("mission_failed")


async def test_without_native_missions_the_agent_flies_each_step(
    make_mission_rig: RigFactory,
) -> None:
    """``native_missions: false``: the agent flies every leg itself (GUIDED), and sends
    the copter home with its own return_to_home at the end."""
    rig = await make_mission_rig(native_missions=False)
    rig.accept(make_task(parcel()))
    released = await rig.event("payload_released", within=120)
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


@pytest.mark.parametrize(
    ("fs_options", "expected"),
    [
        (0, "returns home"),  # ArduCopter's default: the GCS fail-safe's RTL, in AUTO too
        (2, "finishes"),  # FS_OPTIONS bit 1: "continue if in auto"
    ],
)
async def test_when_the_agent_dies_mid_mission_the_autopilot_lands_at_home_by_itself(
    make_mission_rig: RigFactory, fs_options: int, expected: str
) -> None:
    params = {**SIM["params"], "FS_GCS_TIMEOUT": 2, "FS_OPTIONS": fs_options}
    rig = await make_mission_rig(simulator={**SIM, "params": params})
    rig.accept(make_task(parcel("m-dies")))
    await until(lambda: "to_pickup" in [p for p, _ in rig.progress()], within=60)
    address = await agent_dies(rig)
    heard = await listen(address, landed_at_home, within=120)
    assert distance_m(last_position(heard), HOME) < 3
    said = texts(heard)
    if expected == "returns home":
        assert "GCS Failsafe" in said
        assert heard[-1].custom_mode == RTL
        assert "Gripper load released" not in said  # the parcel came back
    else:
        assert "GCS Failsafe - Continuing Auto Mode" in said
        assert "Gripper load released" in said  # delivered with nobody watching
        assert heard[-1].custom_mode == AUTO


async def test_the_autopilots_fence_ends_a_native_mission_and_brings_the_copter_home(
    make_mission_rig: RigFactory,
) -> None:
    """The autopilot's fence (a circle of 45 m round home) holds in AUTO: on the way to
    the drop-off (67 m out) FENCE_ACTION returns the copter home, and the agent reports
    the mission ended by it."""
    rig = await make_mission_rig()
    assert (
        await rig.drone.fence_set("return_to_home", geofence_center=HOME, geofence_radius_m=40)
        == []
    )
    rig.accept(make_task(parcel("m-fenced")))
    failed = await rig.event("mission_failed", within=120)
    assert "RTL" in failed["reason"]
    # (A circle round home, or the same uploaded as an inclusion circle before the
    # agent heard where home is: either way the autopilot's own.)
    assert any(text.endswith("fence breached") for _, _, text in rig.drone.texts)
    await until(lambda: rig.drone.state().armed is False, within=60)
    assert distance_m(rig.drone.state().position or (0, 0), HOME) < 3
    assert releases(rig.drone) == 0 and not rig.events("payload_released")


#: A boat at sea off Barra beach (the demo's Costa Nova station is 720 m east); the
#: pickup, the drop-off and the way between them are water.
BOAT_HOME = (40.6443, -8.7540)
BOAT_PICKUP = offset(BOAT_HOME, 60, 0)
BOAT_DROPOFF = offset(BOAT_HOME, 60, 80)


async def test_a_boat_sails_the_parcel_mission_on_the_water(
    make_mission_rig: RigFactory,
) -> None:
    """No take-off, no descents: the boat is armed, and ArduRover's AUTO sails the plan
    to the pickup, waits there to be loaded, sails to the drop-off, releases once, and
    goes home, where it holds."""
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
    # The next leg is reported as the autopilot reaches the release item, a moment
    # after the release (long on a loaded machine): wait for it, then judge the order.
    await until(lambda: len(rig.progress()) >= 5, within=30)
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
    assert st.mode == "AUTO" and st.armed is True  # a boat holds at home, it does not land
    await until(lambda: rig.drone.mission_progress().finished, within=10)
    assert not rig.events("mission_failed")


async def test_a_mission_the_autopilot_refuses_is_flown_step_by_step(
    make_mission_rig: RigFactory,
) -> None:
    """Another ground station is uploading a mission (and stalls): ArduPilot refuses the
    agent's upload (MAV_MISSION_DENIED). Nothing switches to AUTO; the agent flies the
    parcel itself, step by step, to the same end."""
    rig = await make_mission_rig()
    other = mavutil.mavlink_connection(str(rig.drone.options["connection"]), source_system=200)
    try:
        other.mav.mission_count_send(1, 1, 3, MAV.MAV_MISSION_TYPE_MISSION)
        request = await asyncio.to_thread(
            other.recv_match, type=["MISSION_REQUEST", "MISSION_REQUEST_INT"], blocking=True,
            timeout=5,
        )  # fmt: skip
        assert request is not None and request.seq == 0  # its upload is under way
        rig.accept(make_task(parcel("m-denied")))
        # The platform hears it at once: the autopilot has no mission to finish.
        refused = await rig.event("native_mission_refused", within=30)
        assert refused["mission"] == "m-denied"
        assert refused["reason"].startswith("the autopilot refused the mission: MAV_MISSION_DENIED")
        assert rig.events()[0][0] == "native_mission_refused"  # before any step
        released = await rig.event("payload_released", within=120)
        assert distance_m((released["lat"], released["lon"]), DROPOFF) < 5
        await until(lambda: "returning" in [p for p, _ in rig.progress()], within=30)
        await until(lambda: rig.drone.state().mode == "RTL", within=30)  # its own command
        assert rig.drone.mission_progress() == MissionProgress()  # no plan was taken
        assert releases(rig.drone) == 1 and not rig.events("mission_failed")
    finally:
        other.close()


async def test_when_a_boats_agent_dies_its_autopilot_delivers_and_holds_at_home(
    make_mission_rig: RigFactory,
) -> None:
    """ArduRover's FS_GCS_ENABLE 2 ("continue with mission in Auto"): the agent gone, the
    boat sails on, releases the parcel, goes home and holds there."""
    params = {"FS_GCS_ENABLE": 2}
    rig = await make_mission_rig(
        vehicle_class="boat", origin=list(BOAT_HOME), simulator={"speedup": 6, "params": params}
    )
    rig.accept(
        make_task(parcel("m-boat-dies", pickup=list(BOAT_PICKUP), dropoff=list(BOAT_DROPOFF)))
    )
    await until(lambda: "to_pickup" in [p for p, _ in rig.progress()], within=60)
    address = await agent_dies(rig)

    def complete(msg: Any) -> bool:
        return msg.get_type() == "STATUSTEXT" and msg.text == "Mission Complete"

    heard = await listen(address, complete, within=120)
    said = texts(heard)
    assert "Failsafe - Continuing Auto Mode" in said
    assert "Gripper load released" in said  # delivered with nobody watching
    heard += await listen(address, lambda m: m.get_type() == "GLOBAL_POSITION_INT", within=10)
    assert distance_m(last_position(heard), BOAT_HOME) < 5
    beats = [m for m in heard if m.get_type() == "HEARTBEAT"]
    assert beats[-1].custom_mode == 10 and beats[-1].base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED


async def agent_restarted(make_mission_rig: RigFactory, first_mission_id: str, phase: str) -> Rig:
    """An agent flies parcel ``first_mission_id`` natively and dies once the autopilot is
    at ``phase`` (FS_OPTIONS "continue if in auto": the mission goes on); returns the
    restarted agent's rig on the same autopilot, given no task yet."""
    params = {**SIM["params"], "FS_GCS_TIMEOUT": 2, "FS_OPTIONS": 2}
    rig = await make_mission_rig(simulator={**SIM, "params": params})
    rig.accept(make_task(parcel(first_mission_id)))
    await until(lambda: phase in [p for p, _ in rig.progress()], within=90)
    autopilot = dict(rig.drone.options)
    await agent_dies(rig)
    return await make_mission_rig(autopilot=autopilot)


async def test_an_agent_restarted_mid_mission_follows_the_autopilots_mission(
    make_mission_rig: RigFactory,
) -> None:
    """The companion computer reboots while the autopilot flies the parcel to the
    drop-off (FS_OPTIONS "continue if in auto"). The restarted agent gets the same task
    again (the platform resends it), reads the autopilot's mission back, finds it the one
    it would upload, and follows it from where it is: nothing is uploaded again, so the
    copter does not go back to the pickup, and the parcel is released once."""
    again = await agent_restarted(make_mission_rig, "m-reboot", "to_dropoff")
    again.accept(make_task(parcel("m-reboot")))
    released = await again.event("payload_released", within=90)
    assert distance_m((released["lat"], released["lon"]), DROPOFF) < 5
    await until(lambda: "returning" in [p for p, _ in again.progress()], within=30)
    # Followed from the leg it was on: no upload ("Flight plan received"), no restart.
    assert "Flight plan received" not in [text for _, _, text in again.drone.texts]
    phases = [phase for phase, _ in again.progress()]
    assert phases[0] in ("to_dropoff", "delivery") and "to_pickup" not in phases
    names = [e for e, _ in again.events()]
    assert names.count("parcel_loaded") == 1  # done before: told once
    assert names.count("payload_released") == 1 and releases(again.drone) <= 1
    assert again.drone.state().mode == "AUTO" and not again.events("mission_failed")
    await until(lambda: again.drone.state().armed is False, within=60)
    assert distance_m(again.drone.state().position or (0, 0), HOME) < 3


async def test_a_restarted_agent_uploads_its_mission_when_the_autopilot_flies_another(
    make_mission_rig: RigFactory,
) -> None:
    """The autopilot flies a mission in AUTO that is not the task's (another parcel's):
    read back, it differs, so the agent uploads and flies its own."""
    again = await agent_restarted(make_mission_rig, "m-first", "to_pickup")
    again.accept(make_task(parcel("m-other", dropoff=list(offset(HOME, 30, 40)))))
    await again.event("parcel_loaded", within=90)
    assert "Flight plan received" in [text for _, _, text in again.drone.texts]
    # Flying already: no take-off, its own plan from the start.
    assert [phase for phase, _ in again.progress()][:2] == ["to_pickup", "loading"]
