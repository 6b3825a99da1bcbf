"""The quadcopter's limits, measured at real speed on the simulated ArduCopter.

The simulator brakes as ArduCopter does (its position controller's jerk-limited shaping
with WPNAV_ACCEL 2.5 m/s², WPNAV_ACCEL_Z 1 m/s², PSC_JERK_XY/Z 5 m/s³): a copter
climbing at 2.5 m/s needs some 3.4 m to stop, one flying at 5 m/s some 6.3 m. These
tests hold the keys as a browser does, or move the copter some other way the agent did
not command, and measure how far it gets; the figures are printed (``pytest -s``) and
stated in docs/vehicles/quadcopter.md. Real time: the margins are about the copter's
own speeds.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

from websockets.asyncio.client import ClientConnection

from agents.geo import distance_m, offset
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.dialect import MAV, mavutil
from tests.agents.mavlink_rig import HOME, Rig, RigFactory, join, make_task, sent_off, watch
from tests.agents.waiting import Sampler
from tests.control import command

#: Stated in docs/vehicles/quadcopter.md: never more than this above the ceiling,
#: whatever climbs (the user's keys, a waypoint, the autopilot's own return).
QUAD_MARGIN_M = 2.0
#: ... a copter climbing at 2.5 m/s with ``up`` held ends at most this far above it
#: (it stops the ceiling's margin under it).
QUAD_CEILING_MARGIN_M = 1.0
#: ... and one flying at 5 m/s with ``front`` held at most this far outside the fence.
QUAD_FENCE_MARGIN_M = 1.0
#: ... and one sent out at 5 m/s by someone else (another ground station) at most this
#: far: the tolerance (1 m) and a check's worth of flight, caught on its way out.
QUAD_UNCOMMANDED_FENCE_MARGIN_M = 2.5
#: A waypoint under a speed limit flies at most this much faster than the limit (the
#: autopilot's speed controller settling on the speed it was sent).
QUAD_SPEED_TOLERANCE_MPS = 0.2
#: Sent off faster than the limit by someone else, the drone is at most this much over
#: it before the envelope's correction takes: the tolerance (0.1 m/s), the check and the
#: autopilot's jerk-limited slowing down (measured 0.9-1.0 quiet, up to 1.02 with both
#: cores busy).
QUAD_SPEED_MARGIN_MPS = 1.5
#: Real time, and RTL climbs to 15 m: above a 10 m ceiling.
REAL_TIME = {"speedup": 1, "params": {"RTL_ALT": 1500, "RTL_LOIT_TIME": 500}}


class Track(Sampler):
    """Samples the drone's altitude, distance from home and speed every 20 ms."""

    def __init__(self, drone: MavlinkAdapter) -> None:
        self.drone = drone
        self.highest = self.farthest = self.fastest = 0.0

    def sample(self) -> None:
        t = self.drone.t
        self.highest = max(self.highest, t.alt or 0.0)
        if t.lat is not None and t.lon is not None:
            self.farthest = max(self.farthest, distance_m(HOME, (t.lat, t.lon)))
        self.fastest = max(self.fastest, t.speed or 0.0)


async def take_off_to(ws: ClientConnection, altitude: float) -> None:
    assert (await command(ws, 1, "take_off", altitude_m=altitude))["ok"]
    await watch(ws, lambda d: (d["altitude"] or 0) > altitude - 0.2, 15, f"{altitude} m")


@dataclass
class Held:
    """What holding a key got: every ack, in order, with the distance or altitude of the
    moment it came back."""

    acks: list[tuple[bool, str | None, float]] = field(default_factory=list)

    def accepted_after_first_refusal(self) -> int:
        """Repeats accepted once one had been refused (the key still held)."""
        first = next((i for i, (ok, _, _) in enumerate(self.acks) if not ok), None)
        if first is None:
            return 0
        return sum(1 for ok, _, _ in self.acks[first:] if ok)

    def first_refusal_at(self) -> float | None:
        return next((value for ok, _, value in self.acks if not ok), None)

    def codes(self) -> set[str | None]:
        return {code for ok, code, _ in self.acks if not ok}


async def hold_key(
    ws: ClientConnection, name: str, seconds: float, seq: int, value: Any, **args: Any
) -> tuple[int, Held]:
    """Hold a key as the browser does (a repeat every 100 ms) for ``seconds``, whatever
    the acks say; ``value()`` is recorded with each ack. Returns the next seq."""
    held = Held()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ack = await command(ws, seq, name, **args)
        held.acks.append((bool(ack["ok"]), ack.get("code"), float(value())))
        seq += 1
        await asyncio.sleep(0.1)
    return seq, held


def altitude(rig: Rig) -> float:
    return rig.drone.t.alt or 0.0


def from_home(rig: Rig) -> float:
    t = rig.drone.t
    if t.lat is None or t.lon is None:
        return 0.0
    return distance_m(HOME, (t.lat, t.lon))


@contextlib.asynccontextmanager
async def other_ground_station(rig: Rig) -> AsyncIterator[Any]:
    """A second ground station (system 200) on the simulator's port, as a second
    operator's laptop would be: the agent did not command what it sends."""
    gcs = mavutil.mavlink_connection(rig.drone.config.connection, source_system=200)
    try:
        gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        yield gcs
    finally:
        gcs.close()


# --- held keys --------------------------------------------------------------------------


async def test_a_held_up_key_stops_under_the_ceiling(make_quad_rig: RigFactory):
    """The issue's case: ceiling 15 m, the copter at 10 m, ``up`` at 2.5 m/s repeated
    every 100 ms. ArduCopter 4.7 went to 18.73 m with a gate that looked one second
    ahead and ignored the braking."""
    ceiling = 15.0
    rig = await make_quad_rig(make_task(max_altitude_m=ceiling), simulator=REAL_TIME)
    ws = await join(rig)
    async with Track(rig.drone) as track:
        await take_off_to(ws, 10)
        _, held = await hold_key(ws, "up", 8.0, 2, lambda: altitude(rig), speed_mps=2.5)
        await watch(ws, lambda d: abs(rig.drone.t.climb or 0) < 0.05, 15, "the climb to end")
    print(
        f"\nquad, up at 2.5 m/s from 10 m to a {ceiling:g} m ceiling: first refusal at "
        f"{held.first_refusal_at()} m, highest {track.highest:.2f} m, "
        f"{held.accepted_after_first_refusal()} repeats accepted after it"
    )
    assert track.highest <= ceiling + QUAD_CEILING_MARGIN_M, track.highest
    assert held.codes() <= {"altitude_limit"}
    assert held.accepted_after_first_refusal() == 0
    assert not rig.reported("envelope_breach")
    await ws.close()


async def test_a_held_front_key_stops_at_the_fence_and_never_goes_out_twice(
    make_quad_rig: RigFactory,
):
    """The issue's case: a 40 m fence, ``front`` held at 5 m/s. ArduCopter 4.7 went to
    47.66 m, was brought back, and the still-held key took it out again to 44.3 m."""
    radius = 40.0
    task = make_task(max_altitude_m=20, geofence_center=HOME, geofence_radius_m=radius)
    rig = await make_quad_rig(task, simulator=REAL_TIME)
    ws = await join(rig)
    outside, exits = False, 0

    def distance() -> float:
        nonlocal outside, exits
        now = from_home(rig) > radius
        exits += now and not outside
        outside = now
        return from_home(rig)

    async with Track(rig.drone) as track:
        await take_off_to(ws, 5)
        # 20 s: some 200 repeats, long enough to reach the fence and to keep pushing.
        seq, held = await hold_key(ws, "front", 20.0, 2, distance, speed_mps=5.0)
        await watch(ws, lambda d: (d["speed"] or 0) < 0.1, 15, "the copter to stop")
        distance()
    print(
        f"\nquad, front at 5 m/s to a {radius:g} m fence: first refusal at "
        f"{held.first_refusal_at()} m, farthest {track.farthest:.2f} m, out {exits} times, "
        f"{held.accepted_after_first_refusal()} of {len(held.acks)} repeats accepted after "
        "the first refusal"
    )
    assert track.farthest <= radius + QUAD_FENCE_MARGIN_M, track.farthest
    assert exits <= 1
    assert held.codes() <= {"geofence"}
    assert held.accepted_after_first_refusal() == 0
    # Let go (the browser sends stop), pressed again: still no further.
    assert (await command(ws, seq, "stop"))["ok"]
    ack = await command(ws, seq + 1, "front", speed_mps=5.0)
    assert ack["ok"] is False and ack["code"] == "geofence", ack
    assert "40 m limit" in ack["error"]
    # Backwards, inwards: always.
    assert (await command(ws, seq + 2, "back", speed_mps=2.0))["ok"]
    await ws.close()


# --- the envelope, whatever moved the copter --------------------------------------------


async def test_the_ceiling_holds_whatever_climbs(make_quad_rig: RigFactory):
    ceiling = 10.0
    rig = await make_quad_rig(make_task(max_altitude_m=ceiling), simulator=REAL_TIME)
    drone = rig.drone
    ws = await join(rig)

    def settled_below() -> bool:
        t = drone.t
        return t.alt is not None and t.alt < ceiling and abs(t.climb or 0.0) < 0.1

    async with Track(drone) as track:
        await take_off_to(ws, 8)
        # "up" held: the gate refuses the repeats that would climb past the ceiling;
        # released, the drone ends up below it, whatever the last repeat left it at.
        seq = 2
        end = time.monotonic() + 3
        while time.monotonic() < end:
            await command(ws, seq, "up", speed_mps=1.0)
            seq += 1
            await asyncio.sleep(0.1)
        await watch(ws, lambda d: settled_below(), 10, "below the ceiling")
        # A waypoint at the ceiling: it flies there and no further.
        lat, lon = offset(HOME, 5.0, 0.0)
        ack = await command(ws, seq, "go_to_waypoint", lat=lat, lon=lon, alt_m=ceiling)
        assert ack["ok"]
        await watch(ws, lambda d: (d["altitude"] or 0) > ceiling - 0.3, 10, "the waypoint")
        # The autopilot's return climbs to RTL_ALT (15 m): the envelope lands instead.
        assert (await command(ws, seq + 1, "return_to_home"))["ok"]
        await watch(ws, lambda d: d["is_armed"] is False, 30, "landed")
    print(f"\nquad, {ceiling:g} m ceiling: highest {track.highest:.2f} m")
    assert track.highest <= ceiling + QUAD_MARGIN_M, track.highest
    breaches = rig.reported("envelope_breach")
    assert breaches[-1]["action"] == "land: the return climbs above the ceiling"
    assert all(b["limit"] == "altitude" and b["value"] <= ceiling + 1 for b in breaches)
    assert rig.reported("envelope_restored")  # back below before landing
    await ws.close()


async def test_out_of_the_geofence_the_drone_flies_back_in(make_quad_rig: RigFactory):
    """The drone is out when the fence comes (flown there before the task had one, as
    a previous session may leave it): the envelope brings it back inside."""
    radius = 20.0
    rig = await make_quad_rig(make_task(max_altitude_m=20), simulator=REAL_TIME)
    drone = rig.drone
    ws = await join(rig)
    async with Track(drone) as track:
        await take_off_to(ws, 5)
        lat, lon = offset(HOME, 25.0, 0.0)
        assert (await command(ws, 2, "go_to_waypoint", lat=lat, lon=lon, alt_m=5))["ok"]
        await watch(ws, lambda d: from_home(rig) > 24.5 and d["speed"] < 0.2, 20, "25 m out")
        # The same session's task again, now with a fence (the platform resent it).
        fenced = make_task(max_altitude_m=20, geofence_center=HOME, geofence_radius_m=radius)
        rig.hub.task_accept(fenced)

        def back_inside() -> bool:
            t = drone.t
            assert t.lat is not None and t.lon is not None
            return distance_m(HOME, (t.lat, t.lon)) < radius - 3 and (t.speed or 0) < 0.2

        await watch(ws, lambda d: back_inside(), 20, "back inside, holding")
    print(f"\nquad, {radius:g} m fence, out at 25 m: at most {track.farthest:.2f} m out")
    # Outside by its braking distance at most (5 m at 5 m/s), plus the tolerance.
    assert radius < track.farthest <= radius + 6, track.farthest
    [breach] = rig.reported("envelope_breach")
    assert (
        breach["limit"] == "geofence"
        and breach["action"] == "fly back inside the geofence and hold"
    )
    assert drone.t.mode == 4  # GUIDED: the user's commands work on from here
    await ws.close()


async def test_sent_out_by_another_ground_station_the_drone_is_caught_on_its_way(
    make_quad_rig: RigFactory,
):
    """Another operator's ground station sends the drone 60 m out at the autopilot's
    5 m/s: no command of the agent's to refuse. The envelope sees where it would come
    to rest and brings it back before it is more than the tolerance out."""
    radius = 20.0
    task = make_task(max_altitude_m=20, geofence_center=HOME, geofence_radius_m=radius)
    rig = await make_quad_rig(task, simulator=REAL_TIME)
    drone = rig.drone
    ws = await join(rig)
    async with Track(drone) as track, other_ground_station(rig) as gcs:
        await take_off_to(ws, 5)
        sent_off(gcs, offset(HOME, 60.0, 0.0), 5, target=drone.link.target_or_default())
        await watch(ws, lambda d: bool(rig.reported("envelope_breach")), 20, "the envelope")
        await watch(ws, lambda d: from_home(rig) < radius and d["speed"] < 0.2, 30, "back, holding")
    [breach] = rig.reported("envelope_breach")
    print(
        f"\nquad sent out at 5 m/s by another ground station, {radius:g} m fence: caught at "
        f"{breach['value']:.2f} m (it would have stopped at {breach.get('rest')} m), at most "
        f"{track.farthest:.2f} m out"
    )
    assert breach["limit"] == "geofence"
    assert track.farthest <= radius + QUAD_UNCOMMANDED_FENCE_MARGIN_M, track.farthest
    await ws.close()


async def test_a_waypoint_at_the_autopilots_own_speed_keeps_to_the_limit(
    make_quad_rig: RigFactory,
):
    """Speed 0 asks for the autopilot's own cruise speed (5 m/s here), faster than the
    task's 2 m/s: the gate sends the limit instead, and the drone never breaks it."""
    rig = await make_quad_rig(make_task(max_altitude_m=20, max_speed_mps=2.0), simulator=REAL_TIME)
    drone = rig.drone
    ws = await join(rig)
    async with Track(drone) as track:
        await take_off_to(ws, 5)
        # 20 m: far enough to reach 5 m/s (at WPNAV_ACCEL) were the limit not sent.
        lat, lon = offset(HOME, 20.0, 0.0)
        ack = await command(ws, 2, "go_to_waypoint", lat=lat, lon=lon, alt_m=5, speed_mps=0)
        assert ack["ok"]
        await watch(ws, lambda d: from_home(rig) > 17 and d["speed"] < 0.2, 40, "arrived")
    print(f"\nquad, 2 m/s limit, a waypoint at speed 0: fastest {track.fastest:.2f} m/s")
    assert track.fastest <= 2.0 + QUAD_SPEED_TOLERANCE_MPS, track.fastest
    assert rig.reported("envelope_breach") == []
    await ws.close()


async def test_too_fast_the_drone_slows_down(make_quad_rig: RigFactory):
    """Another operator's ground station sends the drone off at the autopilot's own
    5 m/s, past the task's 2 m/s: no command of the agent's to cap. The envelope slows
    it down."""
    rig = await make_quad_rig(make_task(max_altitude_m=20, max_speed_mps=2.0), simulator=REAL_TIME)
    drone = rig.drone
    ws = await join(rig)
    async with Track(drone) as track, other_ground_station(rig) as gcs:
        await take_off_to(ws, 5)
        sent_off(gcs, offset(HOME, 40.0, 0.0), 5, target=drone.link.target_or_default())
        await watch(ws, lambda d: bool(rig.reported("envelope_restored")), 15, "slowed down")
    [breach] = rig.reported("envelope_breach")
    assert breach["limit"] == "speed" and breach["action"] == "slow down to 1.6 m/s"
    print(f"\nquad, 2 m/s limit, sent off at 5 m/s: fastest {track.fastest:.2f} m/s")
    assert track.fastest <= 2.0 + QUAD_SPEED_MARGIN_MPS, track.fastest
    assert (drone.t.speed or 0) <= 2.0
    await ws.close()
