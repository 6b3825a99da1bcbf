"""Autonomous missions (agents.mission) flown on the MAVLink simulator.

The simulator runs in its own process at 6x flight time with ``WPNAV_SPEED`` at the
missions' 10 m/s; the thermal camera is the synthetic sea rendered from the drone's own
telemetry. Two tests run the whole Agent against a small fake platform (a WebSocket
server speaking the uplink protocol); the others use the same pieces the Agent wires
together (adapter, ControlHub, MissionControl, ThermalFeed) so they can look inside.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve

from agents.config import AgentConfig, ControlConfig
from agents.geo import distance_m, offset
from agents.mission import MissionError, mission_parse
from agents.protocol import (
    PROTOCOL_VERSION,
)
from agents.runtime import Agent
from agents.safety import Refusal
from agents.simulation import simulator_running
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from tests.agents.mission_rig import (
    HOME,
    PRIVATE,
    PUBLIC_PEM,
    SIM,
    VEHICLE,
    RigFactory,
    drone_options,
    make_grant,
    make_task,
    releases,
)
from tests.control import command, recv

#: Holding a position: the arrival radius (3 m) plus the simulator's wobble.
HOLD_M = 5.0
#: A 120 x 80 m search area starting 20 m north of home, lines 30 m apart at 40 m
#: (the camera sees a strip 43 m wide): (north, east) metres from home.
AREA_WAYPOINTS = [(35, 0), (35, 120), (65, 120), (65, 0), (95, 0), (95, 120)]
WAYPOINTS = [list(offset(HOME, n, e)) for n, e in AREA_WAYPOINTS]
PERSON = offset(HOME, 72, 40)  # under the second line, seen flying west


def search(mission_id: str = "m-search", **overrides: Any) -> dict[str, Any]:
    return {
        "kind": "search",
        "id": mission_id,
        "altitude_m": 40,
        "speed_mps": 10,
        "waypoints": WAYPOINTS,
        "start_index": 0,
        "min_confidence": 0.6,
        **overrides,
    }


def delivery(mission_id: str = "m-drop", **overrides: Any) -> dict[str, Any]:
    return {
        "kind": "delivery",
        "id": mission_id,
        "target": list(offset(HOME, 30, 20)),
        "altitude_m": 30,
        "drop_altitude_m": 5,
        "speed_mps": 10,
        **overrides,
    }


async def until_near(
    drone: MavlinkAdapter, point: tuple[float, ...], metres: float, within: float = 5.0
) -> None:
    """Wait for the drone to be within ``metres`` of ``point`` (it overshoots a little
    at corners and settles)."""
    deadline = time.monotonic() + within
    while True:
        here = drone.state().position
        if here is not None and distance_m(here, (point[0], point[1])) <= metres:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"the drone is at {here}, not within {metres} m of {point}")
        await asyncio.sleep(0.05)


# --- a fake platform for whole-agent tests ----------------------------------------------


class FakePlatform:
    """The platform's side of the uplink, enough for one agent: answers ``hello`` with
    ``welcome`` and records everything the agent sends; ``send`` pushes a message."""

    def __init__(self) -> None:
        self.received: list[dict[str, Any]] = []
        self.ws: ServerConnection | None = None
        self.registered = asyncio.Event()
        self.port = 0

    async def handle(self, ws: ServerConnection) -> None:
        hello = json.loads(await ws.recv())
        assert hello["type"] == "hello" and hello["vehicle_id"] == VEHICLE
        await ws.send(
            json.dumps({"type": "welcome", "v": PROTOCOL_VERSION, "heartbeat_interval_s": 1})
        )
        self.ws = ws
        with contextlib.suppress(Exception):
            async for raw in ws:
                msg = json.loads(raw)
                self.received.append(msg)
                if msg["type"] == "profile":
                    self.registered.set()

    async def send(self, msg: dict[str, Any]) -> None:
        assert self.ws is not None
        await self.ws.send(json.dumps(msg))

    async def task(self, mission: dict[str, Any] | None, session: str = "s-1") -> None:
        """A freshly signed task (new nonce), as the platform re-sends one."""
        await self.send({"type": "task", "token": make_task(mission, session).sign(PRIVATE)})

    def events(self, name: str) -> list[dict[str, Any]]:
        return [m["data"] for m in self.received if m["type"] == "event" and m["event"] == name]

    def of_type(self, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.received if m["type"] == kind]

    async def wait(self, predicate: Callable[[], Any], within: float, what: str) -> Any:
        deadline = time.monotonic() + within
        while time.monotonic() < deadline:
            value = predicate()
            if value:
                return value
            await asyncio.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}; received {self.received}")


@contextlib.asynccontextmanager
async def agent_with_platform(
    thermal: dict[str, Any] | None, video: dict[str, Any] | None = None
) -> AsyncIterator[tuple[Agent, FakePlatform]]:
    platform = FakePlatform()
    async with (
        contextlib.AsyncExitStack() as stack,
        serve(platform.handle, "127.0.0.1", 0) as server,
    ):
        port = next(iter(server.sockets)).getsockname()[1]
        simulation = await stack.enter_async_context(simulator_running("mavlink", drone_options()))
        config = AgentConfig(
            platform_url=f"ws://127.0.0.1:{port}",
            vehicle_id=VEHICLE,
            credential="secret",
            platform_public_key=PUBLIC_PEM,
            adapter="mavlink",
            adapter_options=simulation.options,
            control=ControlConfig(host="127.0.0.1", port=0),
            video=video,
            thermal=thermal,
            name="rescue-1",
        )
        agent = Agent(config)
        run = asyncio.create_task(agent.run())
        try:
            await asyncio.wait_for(platform.registered.wait(), 30)
            yield agent, platform
        finally:
            run.cancel()
            with pytest.raises(asyncio.CancelledError):
                await run


# --- the whole agent ----------------------------------------------------------------------


async def test_agent_searches_finds_the_person_and_holds_over_them() -> None:
    thermal = {"source": "synthetic", "persons": [list(PERSON)], "seed": 2}
    video = {"source": "thermal", "ice_host_addresses": ["127.0.0.1"]}
    async with agent_with_platform(thermal, video) as (agent, platform):
        profile = platform.of_type("profile")[0]
        assert profile["video"] is True
        # What its fail-safes do, in the copter's words, for the platform's pages.
        assert profile["safe_actions"]["land"] == "land where it is"
        await platform.task(search())
        found = await platform.wait(lambda: platform.events("person_detected"), 35, "detection")
        hold = await platform.wait(
            lambda: [d for d in platform.events("mission_progress") if d["phase"] == "hold"],
            15,
            "hold",
        )
        assert platform.of_type("task_accepted")
        detected = found[0]
        error = distance_m((detected["lat"], detected["lon"]), PERSON)
        assert error < 5.0, detected
        assert detected["mission"] == "m-search" and detected["confidence"] >= 0.6
        assert detected["waypoint"] == 2  # seen on the second line, after its start
        assert 0.1 <= detected["area_m2"] <= 0.4 and 20 < detected["temperature_c"] < 35
        phases = [(d["phase"], d["waypoint"]) for d in platform.events("mission_progress")]
        assert phases == [
            ("takeoff", None),
            ("transit", None),
            ("search", 0),
            ("search", 1),
            ("search", 2),
            ("hold", 2),
        ]
        assert all(d["of"] == 6 and d["mission"] == "m-search" for d in hold)
        assert not platform.events("search_complete") and not platform.events("mission_failed")
        # It stays over the person (the user keeps watching), at the search altitude.
        assert isinstance(agent.adapter, MavlinkAdapter)
        await until_near(agent.adapter, PERSON, HOLD_M)
        for _ in range(3):
            await asyncio.sleep(0.5)
            await until_near(agent.adapter, PERSON, HOLD_M, within=0.1)
            alt = agent.adapter.state().alt
            assert alt is not None and abs(alt - 40) < 2
        # The same task again (fresh token, same mission): nothing restarts.
        await platform.task(search())
        await platform.wait(lambda: len(platform.of_type("task_accepted")) == 2, 5, "accepted")
        await platform.wait(lambda: len(platform.events("person_detected")) == 2, 5, "re-report")
        assert platform.events("person_detected")[1] == detected
        assert len(platform.events("mission_progress")) == len(phases)
        # The session ends: the mission stops and the drone returns home.
        await platform.send({"type": "end_task", "session_id": "s-1", "reason": "rescued"})
        await platform.wait(lambda: platform.events("task_ended"), 10, "task_ended")
        assert agent.adapter.state().mode == "RTL"
        assert agent.missions is not None and agent.missions.runner is not None
        assert agent.missions.runner.done


async def test_agent_delivery_releases_once_however_often_the_task_comes() -> None:
    async with agent_with_platform(None) as (agent, platform):
        assert isinstance(agent.adapter, MavlinkAdapter)
        await platform.task(delivery())
        await platform.wait(
            lambda: [d for d in platform.events("mission_progress") if d["phase"] == "transit"],
            10,
            "transit",
        )
        await platform.task(delivery())  # re-sent while flying: no restart
        released = await platform.wait(lambda: platform.events("payload_released"), 30, "drop")
        await platform.task(delivery())  # re-sent after the drop: reported, not repeated
        await platform.wait(lambda: len(platform.events("payload_released")) == 2, 5, "again")
        await platform.wait(
            lambda: [d for d in platform.events("mission_progress") if d["phase"] == "hold"],
            20,
            "hold",
        )
        await platform.task(delivery())  # and once more after it finished
        await platform.wait(lambda: len(platform.events("payload_released")) == 3, 5, "third")
        first = released[0]
        assert platform.events("payload_released") == [first, first, first]
        assert distance_m((first["lat"], first["lon"]), tuple(delivery()["target"])) < HOLD_M
        assert releases(agent.adapter) == 1
        phases = [d["phase"] for d in platform.events("mission_progress")]
        assert phases == ["takeoff", "transit", "delivery", "hold"]
        assert len(platform.of_type("task_accepted")) == 4
        state = agent.adapter.state()
        assert state.alt is not None and abs(state.alt - 30) < 2  # climbed back
        assert not platform.events("mission_failed")


# --- MissionControl on the simulator ------------------------------------------------------


async def test_search_without_a_person_completes_and_holds_at_the_last_waypoint(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(search()))
    done = await rig.event("search_complete", 35)
    assert done == {"mission": "m-search", "waypoint": 5}
    await rig.event("mission_progress", 5, count=9)
    assert rig.progress() == [
        ("takeoff", None),
        ("transit", None),
        *[("search", i) for i in range(6)],
        ("hold", 5),
    ]
    assert not rig.events("person_detected")
    await until_near(rig.drone, tuple(WAYPOINTS[5]), HOLD_M)  # it settles there and stays
    await asyncio.sleep(1.0)
    await until_near(rig.drone, tuple(WAYPOINTS[5]), HOLD_M, within=0.1)


async def test_start_index_skips_waypoints_and_a_new_mission_replaces_the_old(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(search("m-first")))
    await rig.event("mission_progress", 15, count=2)  # on its way to the first waypoint
    rig.accept(make_task(search("m-second", start_index=4)))
    await rig.event("search_complete", 35)
    second = [
        (d["phase"], d["waypoint"])
        for _, d in rig.events("mission_progress")
        if d["mission"] == "m-second"
    ]
    # Already in the air: straight to waypoint 4, the ones before are skipped.
    assert second == [("transit", None), ("search", 4), ("search", 5), ("hold", 5)], second
    first = [(e, d.get("phase")) for e, d in rig.events() if d["mission"] == "m-first"]
    # It took off and set off, then stopped without a word when replaced.
    assert first == [("mission_progress", "takeoff"), ("mission_progress", "transit")]
    assert rig.events("search_complete")[0][1] == {"mission": "m-second", "waypoint": 5}


MALFORMED = [
    ({"kind": "rescue", "id": "m"}, "mission.kind"),
    (search(altitude_m=-5), "mission.altitude_m"),
    (search(waypoints=[]), "mission.waypoints"),
    (search(waypoints=[[100, 0]]), "mission.waypoints[0]"),
    (search(start_index=6), "mission.start_index"),
    (search(start_index=True), "mission.start_index"),
    (search(min_confidence=2), "mission.min_confidence"),
    (search(pattern="spiral"), "unknown field"),
    ({**search(), "altitude_m": None}, "mission.altitude_m"),
    (delivery(drop_altitude_m=40), "drop_altitude_m"),
    (delivery(target="here"), "mission.target"),
    ({**delivery(), "id": ""}, "mission.id"),
]


@pytest.mark.parametrize(("mission", "reason"), MALFORMED)
def test_malformed_mission_is_refused_naming_the_field(
    mission: dict[str, Any], reason: str
) -> None:
    with pytest.raises(MissionError) as exc:
        mission_parse(mission)
    assert reason in str(exc.value)


def test_mission_defaults() -> None:
    parsed = mission_parse({"kind": "search", "id": "x", "altitude_m": 40, "waypoints": [HOME]})
    assert (parsed.speed_mps, parsed.start_index, parsed.min_confidence) == (10.0, 0, 0.6)
    drop = mission_parse({"kind": "delivery", "id": "y", "altitude_m": 30, "target": HOME})
    assert (drop.drop_altitude_m, drop.speed_mps) == (5.0, 10.0)


async def test_malformed_mission_is_reported_and_nothing_flies(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    for i, (mission, reason) in enumerate(MALFORMED):
        rig.accept(make_task(mission))
        failed = await rig.event("mission_failed", 2, count=i + 1)
        assert failed["mission"] == (mission["id"] or None)
        assert reason in failed["reason"]
    await asyncio.sleep(0.5)
    assert rig.missions.runner is None and rig.drone.state().armed is False
    assert [e for e, _ in rig.events()] == ["mission_failed"] * len(MALFORMED)


async def test_an_unconfirmed_release_is_never_flown_for_again(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    # As left by a runner stopped while its release_payload was in flight.
    rig.missions.release_attempted.add("m-drop")
    rig.accept(make_task(delivery()))
    failed = await rig.event("mission_failed", 2)
    assert failed == {
        "mission": "m-drop",
        "reason": "the payload release was attempted already and not confirmed",
    }
    await asyncio.sleep(0.5)
    assert rig.missions.runner is None and rig.drone.state().armed is False


async def test_mission_commands_are_checked_inside_the_lock(make_mission_rig: RigFactory) -> None:
    rig = await make_mission_rig()
    rig.hub.task_accept(make_task(None))
    with pytest.raises(Refusal) as exc:
        await rig.hub.mission_execute("s-other", "take_off", {"altitude_m": 10}, epoch=0)
    assert exc.value.code == "no_task"
    with pytest.raises(Refusal) as exc:  # started before a user or a fail-safe acted
        await rig.hub.mission_execute("s-1", "take_off", {"altitude_m": 10}, epoch=-1)
    assert exc.value.code == "overridden"
    with pytest.raises(Refusal) as exc:
        await rig.hub.mission_execute("s-1", "take_off", {"altitude_m": 80}, epoch=0)
    assert exc.value.code == "altitude_limit"
    with pytest.raises(Refusal) as exc:
        await rig.hub.mission_execute("s-1", "take_off", {"altitude": 10}, epoch=0)
    assert exc.value.code == "bad_args"
    assert rig.drone.state().armed is False


async def test_mission_outside_the_task_limits_fails_on_the_ground(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(search(), max_altitude_m=20))
    failed = await rig.event("mission_failed", 5)
    assert "above the 20 m limit" in failed["reason"]
    assert rig.drone.state().armed is False


async def test_adapter_error_fails_the_mission_and_the_drone_holds(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    # 60 km away: the autopilot refuses to reposition that far, in its own words.
    rig.accept(make_task(delivery(target=list(offset(HOME, 60_000, 0)))))
    failed = await rig.event("mission_failed", 20)
    assert "autopilot refused" in failed["reason"] and "too far" in failed["reason"]
    assert [d["phase"] for _, d in rig.events("mission_progress")] == ["takeoff", "transit"]
    here = rig.drone.state()
    await asyncio.sleep(1.5)
    there = rig.drone.state()
    assert here.position is not None and there.position is not None
    assert distance_m(here.position, there.position) < 1.0  # hovering where it was
    assert there.mode == "GUIDED" and there.alt is not None and abs(there.alt - 30) < 2
    assert releases(rig.drone) == 0 and not rig.events("payload_released")


async def wait_battery(drone: MavlinkAdapter) -> None:
    for _ in range(100):
        if drone.state().battery is not None:
            return
        await asyncio.sleep(0.05)
    raise AssertionError("no battery level from the autopilot")


async def test_adapter_refusal_on_the_ground_fails_the_mission(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig(simulator={**SIM, "battery_pct": 20})
    await wait_battery(rig.drone)
    rig.accept(make_task(search()))
    failed = await rig.event("mission_failed", 10)
    assert re.fullmatch(r"battery at 1\d% \(below 25%\): take-off is refused", failed["reason"])
    assert rig.drone.state().armed is False


async def test_the_vehicles_own_low_battery_return_ends_the_mission(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig(simulator={**SIM, "battery_pct": 30, "drain_pct_per_min": 15})
    await wait_battery(rig.drone)
    rig.accept(make_task(search()))
    failed = await rig.event("mission_failed", 20)
    assert failed["reason"] == "interrupted: the vehicle switched to RTL by itself"
    await asyncio.sleep(1.0)
    assert rig.drone.state().mode == "RTL"  # the mission did not fight the return


async def test_a_user_command_takes_over_from_the_mission(make_mission_rig: RigFactory) -> None:
    rig = await make_mission_rig(control=True)
    task = make_task(search())
    rig.accept(task)
    await rig.event("mission_progress", 15, count=3)  # at the first waypoint
    assert rig.server is not None
    ws = await connect(f"ws://127.0.0.1:{rig.server.port}/", compression=None, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": make_grant()}))
    assert (await recv(ws, "welcome"))["role"] == "controller"
    # Joining as controller does not stop the drone: the pattern goes on.
    await rig.event("mission_progress", 15, count=4)
    ack = await command(ws, 1, "stop")
    assert ack["ok"], ack
    failed = await rig.event("mission_failed", 5)
    assert failed["reason"] == "interrupted: the user sent stop"
    count = len(rig.events("mission_progress"))
    await asyncio.sleep(1.5)
    assert len(rig.events("mission_progress")) == count
    assert rig.hub.autonomous is False
    await ws.close()
