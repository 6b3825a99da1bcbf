"""The agent's control server over real sockets, driving the simulated Pi car."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import time
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from agents.control import REFUSAL_REPORT_S, refusal_text
from agents.geo import distance_m
from agents.protocol import (
    generate_keypair,
    load_private_key,
)
from agents.vehicles.base import AdapterError
from tests.agents.car_rig import (
    CAR_COMMANDS,
    SESSION,
    Rig,
    car_rig,
    make_grant,
    make_task,
)
from tests.agents.waiting import until
from tests.control import command, event_named, recv


async def join(rig: Rig, grant: str | None = None) -> tuple[ClientConnection, dict[str, Any]]:
    ws = await connect(rig.url, compression=None, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": grant or make_grant()}))
    return ws, await recv(ws, "welcome")


async def close_code(ws: ClientConnection, within: float = 3.0) -> int | None:
    try:
        while True:
            await asyncio.wait_for(ws.recv(), within)
    except ConnectionClosed:
        return ws.close_code


async def keep_alive(ws: ClientConnection, seconds: float) -> float:
    """Act as a live controller: a keepalive every 100 ms. Returns when the last went."""
    end = time.monotonic() + seconds
    last = time.monotonic()
    while time.monotonic() < end:
        await ws.send(json.dumps({"type": "keepalive"}))
        last = time.monotonic()
        await asyncio.sleep(0.1)
    return last


# --- driving -----------------------------------------------------------------------------


async def test_controller_drives_the_car_and_acks_carry_seq(rig: Rig):
    ws, welcome = await join(rig)
    assert welcome["role"] == "controller"
    assert {c["name"] for c in welcome["commands"]} >= set(CAR_COMMANDS)
    start = rig.world.position

    ack = await command(ws, 7, "forward", speed=1.0)
    assert ack == {"type": "ack", "seq": 7, "ok": True, "error": None}
    await keep_alive(ws, 1.0)
    moved = rig.world.position
    assert moved != start
    heading_before = rig.world.heading_deg
    assert (await command(ws, 8, "right", speed=1.0))["ok"]
    await keep_alive(ws, 0.5)
    assert rig.world.heading_deg != heading_before
    assert (await command(ws, 9, "stop"))["ok"]

    tilt = rig.car.telemetry()["camera_tilt"]
    assert (await command(ws, 10, "camera_up", step_deg=30))["seq"] == 10
    assert rig.car.telemetry()["camera_tilt"] != tilt
    assert rig.events("user_connected")[0]["user"] == "alice"
    await ws.close()


async def test_the_welcome_describes_every_topic_in_words(rig: Rig):
    # The page shows "Battery 82 %", not "battery_level 82.0391": each topic comes with
    # a label, and numbers with their unit and precision.
    ws, welcome = await join(rig)
    info = welcome["telemetry_info"]
    assert set(info) == set(welcome["telemetry"])
    assert info["battery_level"] == {"label": "Battery", "unit": "%", "decimals": 0}
    assert info["distance_ahead"] == {"label": "Obstacle ahead", "unit": "m", "decimals": 2}
    assert all(entry["label"] and "_" not in entry["label"] for entry in info.values())
    await ws.close()


async def test_telemetry_arrives_at_the_subscribed_rate(rig: Rig):
    ws, _ = await join(rig)
    await ws.send(
        json.dumps({"type": "subscribe", "topics": ["battery_level", "location"], "rate_hz": 10})
    )
    first = await recv(ws, "telemetry")
    assert set(first["data"]) == {"battery_level", "location"}
    count, start = 0, time.monotonic()
    while time.monotonic() - start < 2.0:
        await recv(ws, "telemetry")
        count += 1
    assert 14 <= count <= 24  # 10 Hz for 2 s, loose for a busy machine
    await ws.send(json.dumps({"type": "subscribe", "topics": ["warp_drive"], "rate_hz": 1}))
    assert (await recv(ws, "error"))["code"] == "unknown_topic"
    await ws.close()


async def test_telemetry_goes_on_after_a_path_breaks_under_a_user_still_here(rig: Rig):
    """A relayed user's path breaks when the uplink carrying it reconnects, and comes
    back: their telemetry must not end with that one failed send."""
    ws, _ = await join(rig)
    await ws.send(json.dumps({"type": "subscribe", "topics": ["battery_level"], "rate_hz": 10}))
    await recv(ws, "telemetry")
    (client,) = rig.hub.clients.values()
    send = client.link.send
    broken = 0

    async def breaks_twice(message: Any) -> None:
        nonlocal broken
        if broken < 2:
            broken += 1
            raise ConnectionError("the relay's uplink is reconnecting")
        await send(message)

    client.link.send = breaks_twice  # type: ignore[method-assign]
    await until(lambda: broken == 2, what="two sends to fail")
    for _ in range(5):
        await recv(ws, "telemetry")  # on again
    await ws.close()


async def test_ping_is_answered_and_agent_measures_rtt(rig: Rig):
    ws, _ = await join(rig)
    await ws.send(json.dumps({"type": "ping", "t": 123.5}))
    pong = await recv(ws, "pong")
    assert pong["t"] == 123.5 and pong["server_t"] > 0
    # Reading answers the agent's pings; after one, the agent knows the round trip.
    with pytest.raises(TimeoutError):
        await recv(ws, "nothing-else", within=1.2)
    controller = rig.hub.controller
    assert controller is not None and controller.rtt_ms is not None and controller.rtt_ms < 500
    await ws.close()


# --- who may connect ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("grant", "code"),
    [
        # Signed by a key the agent does not hold: its kid names no trusted key.
        (lambda: make_grant(key=load_private_key(generate_keypair()[0])), "unknown_key"),
        (lambda: make_grant(ttl=-10), "expired"),
        (lambda: make_grant(vehicle="car-other"), "wrong_vehicle"),
        (lambda: "not.a-token", "bad_token"),
    ],
)
async def test_bad_grants_are_refused(rig: Rig, grant, code):
    ws = await connect(rig.url, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": grant()}))
    error = await recv(ws, "error")
    assert error["code"] == code
    assert await close_code(ws) == 4401
    assert rig.hub.controller is None


async def test_replayed_grant_is_refused(rig: Rig):
    token = make_grant()
    first, _ = await join(rig, token)
    await first.close()
    ws = await connect(rig.url, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": token}))
    assert (await recv(ws, "error"))["code"] == "replayed"
    assert await close_code(ws) == 4401


async def test_grant_for_another_session_is_refused(rig: Rig):
    ws = await connect(rig.url, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": make_grant(session="other")}))
    assert (await recv(ws, "error"))["code"] == "no_task"
    assert await close_code(ws) == 4403


async def test_anything_before_auth_closes(rig: Rig):
    ws = await connect(rig.url, proxy=None)
    await ws.send(json.dumps({"type": "command", "seq": 1, "name": "forward"}))
    assert (await recv(ws, "error"))["code"] == "unauthorized"
    assert await close_code(ws) == 4401


async def test_second_controller_cannot_steer_until_it_takes_control(rig: Rig):
    first, _ = await join(rig)
    second, welcome = await join(rig)
    assert welcome["role"] == "viewer"
    refused = await command(second, 1, "forward")
    assert not refused["ok"] and refused["code"] == "view_only"
    assert rig.world.efforts == (0.0, 0.0)

    assert (await command(first, 1, "forward", speed=0.8))["ok"]
    await asyncio.sleep(0.1)
    assert rig.world.efforts != (0.0, 0.0)
    # The other tab takes over: the car's inputs are zeroed before it may steer.
    await second.send(json.dumps({"type": "take_control"}))
    assert (await recv(second, "role"))["role"] == "controller"
    assert (await recv(first, "role"))["role"] == "viewer"
    await asyncio.sleep(0.1)
    assert rig.world.efforts == (0.0, 0.0)
    assert (await command(first, 2, "forward"))["code"] == "view_only"
    assert (await command(second, 2, "backward"))["ok"]
    # The platform hears of the hand-over, and of control put down.
    (handover,) = rig.events("control_handover")
    assert handover["user"] == "alice" and handover["from"] != handover["to"]
    await second.send(json.dumps({"type": "release_control"}))
    assert (await recv(second, "role"))["role"] == "viewer"
    (released,) = rig.events("control_released")
    assert released["from"] == handover["to"]
    await first.close()
    await second.close()


async def test_viewer_grant_never_controls(rig: Rig):
    ws, welcome = await join(rig, make_grant(role="viewer", user="bob"))
    assert welcome["role"] == "viewer"
    await ws.send(json.dumps({"type": "take_control"}))
    assert (await recv(ws, "error"))["code"] == "view_only"
    await ws.close()


# --- safety ------------------------------------------------------------------------------


async def test_obstacle_stops_the_car_and_refuses_forward(rig: Rig):
    ws, _ = await join(rig)
    assert (await command(ws, 1, "forward", speed=0.5))["ok"]
    rig.world.place_obstacle_ahead(0.15)
    await keep_alive(ws, 0.3)
    assert rig.world.speed_mps == pytest.approx(0.0, abs=1e-3)
    refused = await command(ws, 2, "forward")
    assert not refused["ok"] and refused["code"] == "obstacle"
    assert (await command(ws, 3, "backward", speed=0.3))["ok"]
    assert rig.events("command_refused")[0]["code"] == "obstacle"
    await ws.close()


async def test_killed_client_stops_the_car_and_platform_is_told(rig: Rig):
    ws, _ = await join(rig)
    assert (await command(ws, 1, "forward", speed=1.0))["ok"]
    await asyncio.sleep(0.1)
    assert rig.world.speed_mps > 0
    killed_at = time.monotonic()
    ws.transport.abort()  # as if the browser's process died: no close handshake
    for _ in range(200):  # poll the simulated car for up to 2 s
        if rig.world.speed_mps == 0:
            break
        await asyncio.sleep(0.01)
    # The closed socket is noticed at once, well within the 500 ms link-loss timeout: the
    # car stops; the fail-safe follows once the timeout passed with nobody back (a
    # reloading page would have taken the controls back).
    assert time.monotonic() - killed_at < 0.5
    await until(
        lambda: rig.events("failsafe") == [{"cause": "link_lost", "action": "stop"}],
        what="the fail-safe once the link-loss timeout passed",
    )


async def test_silent_controller_triggers_failsafe_after_timeout(rig: Rig):
    ws, _ = await join(rig)
    assert (await command(ws, 1, "forward", speed=1.0))["ok"]
    silent_at = await keep_alive(ws, 0.8)
    assert rig.world.speed_mps > 0  # keepalives hold the link
    # The agent tells the user why it stopped.
    await event_named(ws, "failsafe", within=3)
    # Not before the 500 ms timeout; the upper bound is loose for a busy machine.
    assert 0.45 <= time.monotonic() - silent_at <= 1.5
    assert rig.car.telemetry()["motors"] == {"left": 0.0, "right": 0.0}
    # The user is still connected and may drive again.
    assert (await command(ws, 2, "forward"))["ok"]
    await ws.close()


async def test_geofence_refuses_leaving_but_allows_coming_back(rig: Rig):
    here = rig.car.state().position
    await rig.hub.task_end(SESSION, reason="next test", action="stop")
    rig.hub.task_accept(make_task(session="fenced", geofence_center=here, geofence_radius_m=0.2))
    ws, _ = await join(rig, make_grant(session="fenced"))
    refused = await command(ws, 1, "forward", speed=1.0)
    assert not refused["ok"] and refused["code"] == "geofence"
    await ws.close()


async def test_latency_past_hard_limit_only_stop_passes(rig: Rig):
    await rig.hub.task_end(SESSION, reason="next test", action="stop")
    rig.hub.task_accept(make_task(session="laggy", latency_soft_ms=1, latency_hard_ms=2))
    ws, _ = await join(rig, make_grant(session="laggy"))
    rig.hub.controller.rtt_ms = 50.0  # as measured on a slow link
    refused = await command(ws, 1, "forward")
    assert not refused["ok"] and refused["code"] == "latency"
    assert (await command(ws, 2, "stop"))["ok"]
    await ws.close()


async def test_unknown_and_bad_commands_are_refused_with_reasons(rig: Rig):
    ws, _ = await join(rig)
    assert (await command(ws, 1, "fly"))["code"] == "unknown_command"
    assert (await command(ws, 2, "forward", speed=7))["code"] == "bad_args"
    assert (await command(ws, 3, "forward", warp=1))["code"] == "bad_args"
    assert rig.hub.stats["refused"] == 3
    await ws.close()


async def test_revoked_task_drops_users_and_stops(rig: Rig):
    ws, _ = await join(rig)
    assert (await command(ws, 1, "forward"))["ok"]
    assert await rig.hub.task_end(SESSION, reason="monitor stop", action="stop")
    event = await recv(ws, "event")
    assert event["event"] == "session_ended" and event["data"]["reason"] == "monitor stop"
    assert await close_code(ws) == 4403
    assert rig.car.telemetry()["motors"] == {"left": 0.0, "right": 0.0}
    assert rig.events("task_ended") == [{"reason": "monitor stop"}]


# --- bad input ---------------------------------------------------------------------------


async def test_bad_frames_get_errors_and_the_session_continues(rig: Rig):
    ws, _ = await join(rig)
    for frame in [
        "{",
        "[]",
        '{"type":"nope"}',
        '{"type":"command","seq":-1,"name":"x"}',
        b"\x00\xff binary",
    ]:
        await ws.send(frame)
        assert (await recv(ws, "error"))["code"] in {"bad_json", "unknown_type", "bad_field"}
    assert (await command(ws, 5, "stop"))["ok"]
    await ws.close()


async def test_oversized_frame_closes_only_that_client(rig: Rig):
    other, _ = await join(rig, make_grant(role="viewer", user="bob"))
    ws, _ = await join(rig)
    await ws.send(json.dumps({"type": "keepalive", "pad": "x" * 100_000}))
    assert await close_code(ws) == 1009
    await other.send(json.dumps({"type": "ping", "t": 1}))
    assert (await recv(other, "pong"))["t"] == 1
    await other.close()


async def test_flood_is_throttled_then_disconnected(rig: Rig):
    ws, _ = await join(rig)
    for _ in range(1500):
        await ws.send('{"type":"keepalive"}')
    codes = set()
    try:
        while True:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 3))
            codes.add(msg.get("code"))
    except ConnectionClosed:
        pass
    assert "rate_limited" in codes and ws.close_code == 4429
    # Others are still served.
    again, welcome = await join(rig)
    assert welcome["role"] == "controller"
    await again.close()


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(frames=st.lists(st.one_of(st.text(max_size=200), st.binary(max_size=200)), max_size=8))
async def test_fuzzed_frames_never_break_the_agent(frames):
    async with car_rig({}) as rig:
        ws, _ = await join(rig)
        for frame in frames:
            await ws.send(frame)
        # Every frame was answered or ignored; the agent still serves this client.
        assert (await command(ws, 99, "stop"))["seq"] == 99
        await ws.close()


# --- what the user and the platform are told ---------------------------------------------


def test_refusal_texts_name_the_command():
    assert refusal_text("up", "arm the motors first") == "up: arm the motors first"
    assert refusal_text("up", "the drone is on the ground: take off first (up)").endswith("(up)")
    # A word, not a substring: "unsupported" does not name "up".
    assert refusal_text("up", "autopilot refused it: unsupported") == (
        "up: autopilot refused it: unsupported"
    )


async def test_every_refusal_the_user_sees_names_the_command(rig: Rig):
    ws, _ = await join(rig)
    viewer, _ = await join(rig, make_grant(role="viewer", user="bob"))
    acks = [
        await command(ws, 1, "fly"),
        await command(ws, 2, "forward", speed=7),
        await command(ws, 3, "forward", warp=1),
        await command(viewer, 1, "backward"),
    ]
    assert [a["code"] for a in acks] == ["unknown_command", "bad_args", "bad_args", "view_only"]
    assert "fly" in acks[0]["error"]
    assert acks[1]["error"].startswith("forward: ") and "speed" in acks[1]["error"]
    assert acks[2]["error"].startswith("forward: ") and "warp" in acks[2]["error"]
    assert acks[3]["error"].startswith("backward: ")

    async def vehicle_says_no(name: str, args: Any) -> None:
        raise AdapterError("the vehicle said no", code="refused")

    rig.car.execute = vehicle_says_no  # type: ignore[method-assign]
    ack = await command(ws, 4, "left")
    assert ack["code"] == "refused" and ack["error"] == "left: the vehicle said no"
    await rig.hub.task_end(SESSION, reason="next test", action="stop")
    rig.hub.task_accept(make_task(session="laggy", latency_soft_ms=1, latency_hard_ms=2))
    ws, _ = await join(rig, make_grant(session="laggy"))
    rig.hub.controller.rtt_ms = 50.0
    ack = await command(ws, 1, "backward")
    assert ack["code"] == "latency" and ack["error"].startswith("backward refused: round trip")


async def refuse(ws: ClientConnection, seqs: range, name: str = "fly", **args: Any) -> int:
    """Send refused commands as fast as they go, then wait for every ack. Returns how
    many the gate refused (the rest found the command queue full: "busy")."""
    for seq in seqs:
        await ws.send(json.dumps({"type": "command", "seq": seq, "name": name, "args": args}))
    codes = [(await recv(ws, "ack"))["code"] for _ in seqs]
    return sum(code != "busy" for code in codes)


async def test_refused_commands_are_reported_at_once_then_at_most_once_a_second(rig: Rig):
    ws, _ = await join(rig)

    def refusals() -> list[tuple[float, dict[str, Any]]]:
        return [
            (at, data)
            for at, (event, _, data) in zip(rig.stamps, rig.reports, strict=True)
            if event == "command_refused"
        ]

    def counted() -> int:
        return sum(data["count"] for _, data in refusals())

    # A flooding controller: the first refusal is reported at once...
    total = await refuse(ws, range(1, 41))
    (_, first), *_ = refusals()
    assert first == {
        "name": "fly",
        "code": "unknown_command",
        "reason": "'fly' is not a command of this vehicle",
        "count": 1,
    }
    # ... the others in one summary a second later.
    await until(lambda: counted() == total, what="the summary")
    assert [data["count"] for _, data in refusals()] == [1, total - 1]
    assert refusals()[1][1]["codes"] == {"unknown_command": total - 1}
    # Refusals going on for a while, of two kinds: at most one report a second.
    seq = 41
    for _ in range(12):
        total += await refuse(ws, range(seq, seq + 5), "forward", speed=9)
        total += await refuse(ws, range(seq + 5, seq + 7))
        seq += 7
        await asyncio.sleep(0.2)  # the pace of the refusals, not a wait for a result
    await until(lambda: counted() == total, what="every refusal counted")
    stamps = [at for at, _ in refusals()]
    assert all(b - a >= REFUSAL_REPORT_S - 0.01 for a, b in itertools.pairwise(stamps))
    last = refusals()[-1][1]
    assert (last["name"], last["code"]) == ("fly", "unknown_command")
    assert set(last["codes"]) <= {"bad_args", "unknown_command"}
    # Pending refusals reach the platform before the end of the task, none after it.
    total += await refuse(ws, range(seq, seq + 3))
    await rig.hub.task_end(SESSION, reason="done", action="stop")
    events = [event for event, _, _ in rig.reports]
    assert events[-1] == "task_ended" and counted() == total
    assert rig.hub._refusals.timer is None and rig.hub._refusals.session is None


async def test_a_controller_back_after_a_silence_is_reported_once(rig: Rig):
    ws, _ = await join(rig)
    assert (await command(ws, 1, "forward", speed=0.5))["ok"]
    silent_at = time.monotonic()
    await event_named(ws, "failsafe", within=3)  # 500 ms of nothing
    await ws.send(json.dumps({"type": "keepalive"}))
    back = await event_named(ws, "link_recovered")
    assert back["data"]["user"] == "alice"
    after_ms = back["data"]["after_ms"]
    assert 500 <= after_ms <= (time.monotonic() - silent_at) * 1000 + 50
    assert rig.events("link_recovered") == [{"user": "alice", "after_ms": after_ms}]
    # Once: further input is just input.
    await ws.send(json.dumps({"type": "keepalive"}))
    assert (await command(ws, 2, "stop"))["ok"]
    assert len(rig.events("link_recovered")) == 1
    await ws.close()
    # A closed socket is no silence: a new connection is not a recovery.
    again, _ = await join(rig)
    assert (await command(again, 1, "forward", speed=0.5))["ok"]
    again.transport.abort()
    await until(lambda: len(rig.events("failsafe")) == 2, what="the second fail-safe")
    third, _ = await join(rig)
    assert (await command(third, 1, "stop"))["ok"]
    assert len(rig.events("link_recovered")) == 1
    await third.close()


# --- the safety envelope -----------------------------------------------------------------

#: A car at its full 0.5 m/s is stopped within this distance outside its geofence (the
#: tolerance, 5 % of a 1 m radius, plus up to two 100 ms checks of travel, with room
#: for a busy machine); see docs/vehicles/car.md.
CAR_FENCE_MARGIN_M = 0.3


async def live_until_event(ws: ClientConnection, name: str, within: float = 5.0) -> dict[str, Any]:
    """Stay a live controller (keepalives every 100 ms) until event ``name`` arrives."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        await ws.send(json.dumps({"type": "keepalive"}))
        with contextlib.suppress(TimeoutError):
            msg = await recv(ws, "event", within=0.1)
            if msg["event"] == name:
                return msg
    raise AssertionError(f"no {name} event")


async def _command_keeping_events(
    ws: ClientConnection, seq: int, events: list[dict[str, Any]], **args: Any
) -> dict[str, Any]:
    """``forward`` as number ``seq``; its ack. The events that come before it are kept in
    ``events`` (:func:`tests.control.command` passes over them)."""
    await ws.send(json.dumps({"type": "command", "seq": seq, "name": "forward", "args": args}))
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), 3))
        if msg["type"] == "ack":
            return msg
        if msg["type"] == "event":
            events.append(msg)
        elif msg["type"] == "ping":
            await ws.send(json.dumps({"type": "pong", "t": msg["t"]}))


async def test_a_car_rolling_out_of_its_geofence_is_stopped(rig: Rig):
    here = rig.car.state().position
    assert here is not None
    await rig.hub.task_end(SESSION, reason="next test", action="stop")
    rig.hub.task_accept(make_task(session="fenced", geofence_center=here, geofence_radius_m=1.0))
    ws, _ = await join(rig, make_grant(session="fenced"))
    overrides = rig.hub.overrides
    # "forward" held: once a repeat would leave the fence the gate refuses it, but the
    # motors keep the last accepted speed: only the envelope stops the car.
    seq, farthest, codes = 1, 0.0, set()
    told: list[dict[str, Any]] = []  # the events the user was sent, kept while driving
    deadline = time.monotonic() + 8
    while not rig.events("envelope_breach"):
        assert time.monotonic() < deadline, f"still driving: {rig.car.state()}"
        codes.add((await _command_keeping_events(ws, seq, told, speed=1.0)).get("code"))
        farthest = max(farthest, distance_m(here, rig.car.state().position))
        seq += 1
        await asyncio.sleep(0.1)
    assert "geofence" in codes
    while not any(e["event"] == "envelope_breach" for e in told):
        told.append(await recv(ws, "event"))
    breach = next(e for e in told if e["event"] == "envelope_breach")["data"]
    assert breach["limit"] == "geofence" and breach["action"] == "stop"
    assert breach["limit_value"] == 1.0 and 1.0 < breach["value"] <= 1.0 + CAR_FENCE_MARGIN_M
    assert rig.events("envelope_breach") == [breach]
    assert rig.hub.overrides > overrides and "envelope" in rig.hub.override_reason
    # The key is still held: the car stays where it stopped, outside but close.
    for _ in range(5):
        assert (await command(ws, seq, "forward", speed=1.0))["code"] == "geofence"
        seq += 1
        farthest = max(farthest, distance_m(here, rig.car.state().position))
    # The motors are off; the simulated world shows it at its next step, which a loaded
    # machine may run late: wait for that step rather than read the one before it.
    assert rig.car.telemetry()["motors"] == {"left": 0.0, "right": 0.0}
    for _ in range(250):  # up to 5 s
        if rig.world.speed_mps == 0.0:
            break
        await asyncio.sleep(0.02)
    assert rig.world.speed_mps == 0.0
    farthest = max(farthest, distance_m(here, rig.car.state().position))
    print(
        f"\ncar at 0.5 m/s, 1 m fence: breach seen at {breach['value']:.2f} m, "
        f"stopped at most {farthest:.2f} m out"
    )
    assert farthest <= 1.0 + CAR_FENCE_MARGIN_M
    # Backing in brings it inside; the platform hears it is back.
    while distance_m(here, rig.car.state().position) > 0.8:
        assert (await command(ws, seq, "backward", speed=1.0))["ok"]
        seq += 1
        await asyncio.sleep(0.1)
    assert (await command(ws, seq, "stop"))["ok"]
    restored = await live_until_event(ws, "envelope_restored")
    assert restored["data"]["limit"] == "geofence"
    assert rig.events("envelope_restored")[0]["limit"] == "geofence"
    await rig.hub.task_end("fenced", reason="done", action="stop")
    assert rig.hub._envelope is None  # the watch ends with the task


async def test_a_new_connection_of_the_user_takes_over_from_a_controller_gone_silent(rig: Rig):
    """The controller's socket still counts open here but nothing comes on it (a relay
    cut with its platform process): the fail-safe acts, and the user's new connection
    is the controller at once, no take_control needed; the platform hears the hand-over."""
    old, _ = await join(rig)
    assert (await command(old, 1, "forward", speed=0.5))["ok"]
    await event_named(old, "failsafe", within=3)  # 500 ms of nothing
    new, welcome = await join(rig)
    assert welcome["role"] == "controller"
    assert (await recv(old, "role"))["role"] == "viewer"
    assert (await command(new, 2, "forward", speed=0.5))["ok"]
    assert rig.events("control_handover")[-1]["role"] == "controller"
    await old.close()
    await new.close()


async def test_a_second_connection_of_the_user_watches_while_the_controller_drives(rig: Rig):
    """A live controller keeps the controls: another connection of the same user is a
    viewer until it asks for them (take_control)."""
    driving, _ = await join(rig)
    assert (await command(driving, 1, "forward", speed=0.5))["ok"]
    other, welcome = await join(rig)
    assert welcome["role"] == "viewer"
    await driving.close()
    await other.close()
