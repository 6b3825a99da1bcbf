"""The safety envelope's logic (agents.envelope), on a clock the tests move.

The vehicles' own answers to a breach are tested with their simulators in test_car.py,
test_mavlink.py and test_spektrum.py.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest

from agents.envelope import (
    DWELL_S,
    MIN_REPEAT_S,
    REPEAT_S,
    RESTORE_S,
    Envelope,
    EnvelopeWatch,
    band_for,
)
from agents.geo import offset
from agents.protocol import Limits
from agents.vehicles.base import Braking, Breach, Stopping, VehicleState

CENTRE = (40.0, -8.0)


def at(alt: float | None = None, *, north: float | None = None, speed: float | None = None):
    position = None if north is None else offset(CENTRE, north, 0.0)
    return VehicleState(
        alt=alt,
        lat=None if position is None else position[0],
        lon=None if position is None else position[1],
        speed_mps=speed,
    )


def run(envelope: Envelope, values: list[tuple[float, float]]) -> list[tuple[float, str]]:
    """Feed (time, altitude) pairs; returns (time, step kind) of every step."""
    out = []
    for now, alt in values:
        out += [(now, step.kind) for step in envelope.update(at(alt), now)]
    return out


def test_bands_scale_with_the_limit_and_are_capped():
    small, large = band_for("altitude", 6.0), band_for("altitude", 60.0)
    assert (small.tolerance, small.margin) == pytest.approx((0.3, 1.2))
    assert (large.tolerance, large.margin) == (0.5, 2.0)
    assert large.target == 58.0 and large.restore_below == 59.0
    fence = band_for("geofence", 100.0)
    assert (fence.tolerance, fence.margin) == (1.0, 5.0)
    speed = band_for("speed", 2.0)
    assert (speed.tolerance, speed.margin) == pytest.approx((0.1, 0.4))


def test_a_climb_past_the_tolerance_is_one_breach_with_a_target_inside():
    envelope = Envelope(Limits(max_altitude_m=60))
    steps = envelope.update(at(60.4), 0.0)  # within the 0.5 m tolerance: not yet
    assert steps == []
    [step] = envelope.update(at(60.6), 0.1)
    assert step.kind == "breach"
    assert step.breach == Breach("altitude", 60.6, 60.0, 58.0)
    assert envelope.breached == ["altitude"]


def test_a_vehicle_sitting_just_above_the_limit_is_a_breach_after_the_dwell():
    envelope = Envelope(Limits(max_altitude_m=10))
    steps = run(envelope, [(t / 10, 10.2) for t in range(0, 30)])
    assert steps == [(DWELL_S, "breach")]


def test_flying_at_the_speed_limit_is_no_breach_but_a_real_overshoot_is():
    """An autopilot asked for exactly the limit's speed reports a few cm/s over it all
    along (ArduCopter: 5.05 m/s at 5 m/s): no breach. More than half the tolerance over
    it for the dwell, or past the tolerance, is."""
    limits = Limits(max_speed_mps=5)
    band = band_for("speed", 5.0)
    envelope = Envelope(limits)
    steady = [(t / 10, 5.05 + 0.02 * (t % 3)) for t in range(100)]  # 10 s at 5.05-5.09
    assert [s for now, v in steady for s in envelope.update(at(speed=v), now)] == []
    over = band.limit_value + band.tolerance * 0.75  # 5.19: past half the tolerance
    steps = [(now, s.kind) for now, v in [(10 + t / 10, over) for t in range(30)]
             for s in envelope.update(at(speed=v), now)]  # fmt: skip
    assert steps == [(10 + DWELL_S, "breach")]
    [step] = Envelope(limits).update(at(speed=5.0 + band.tolerance + 0.01), 0.0)
    assert step.kind == "breach"


def test_a_vehicle_that_could_no_longer_stop_inside_is_caught_on_its_way_out():
    """With its velocity and its braking, a breach is where the vehicle would come to
    rest: a climb at 3 m/s braking at 1 m/s² 2.5 m under the ceiling is caught there,
    and the recovery aims where it is (never further out than the margin's target)."""
    braking = Braking(vertical=Stopping(decel_mps2=1.0, reaction_s=0.2))
    envelope = Envelope(Limits(max_altitude_m=10))
    climbing = VehicleState(alt=7.5, velocity=(0.0, 0.0, 3.0))
    [step] = envelope.update(climbing, 0.0, braking)
    assert step.kind == "breach"
    assert step.breach.value == 7.5 and step.breach.target == 7.5  # under the 8 m target
    assert step.breach.rest == pytest.approx(7.5 + 0.6 + 4.5 + 0.3)  # reaction, brake, check
    # Slow enough to stop within the tolerance: nothing.
    slow = VehicleState(alt=9.0, velocity=(0.0, 0.0, 0.5))
    assert Envelope(Limits(max_altitude_m=10)).update(slow, 0.0, braking) == []
    # Heading out of a 40 m fence at 5 m/s, 34 m from its centre: it would stop 41.5 m
    # out, past the 1 m tolerance: caught.
    fence = Envelope(Limits(geofence_center=CENTRE, geofence_radius_m=40))
    lat, lon = offset(CENTRE, 34.0, 0.0)
    out = VehicleState(lat=lat, lon=lon, velocity=(5.0, 0.0, 0.0))
    across = Braking(horizontal=Stopping(decel_mps2=2.5, reaction_s=0.4))
    [step] = fence.update(out, 0.0, across)
    assert step.breach.limit == "geofence" and step.breach.rest == pytest.approx(41.5, abs=0.01)
    # Still heading out, it is not back inside, however long it stays under the limit.
    later = [fence.update(out, 0.5 + t / 10, across) for t in range(30)]
    assert not any(later) and fence.breached == ["geofence"]
    still = VehicleState(lat=lat, lon=lon, velocity=(0.0, 0.0, 0.0))
    steps = [s.kind for t in range(15) for s in fence.update(still, 4.0 + t / 10, across)]
    assert steps == ["restored"]
    # ... and nothing when it comes back.
    back = VehicleState(lat=lat, lon=lon, velocity=(-5.0, 0.0, 0.0))
    assert (
        Envelope(Limits(geofence_center=CENTRE, geofence_radius_m=40)).update(back, 0.0, across)
        == []
    )


def test_noise_around_the_limit_does_not_chatter():
    envelope = Envelope(Limits(max_altitude_m=10))
    # Across the limit and back every 100 ms, never for long: no breach at all.
    wobble = [(t / 10, 10.2 if t % 2 else 9.9) for t in range(0, 100)]
    assert run(envelope, wobble) == []
    # Once breached, in and out near the limit: one breach, recoveries, no restore
    # until the value stayed inside by half the margin for RESTORE_S.
    envelope = Envelope(Limits(max_altitude_m=10))
    values = [(0.0, 11.0)] + [(0.1 + t / 10, 10.4 if t % 3 else 9.6) for t in range(50)]
    kinds = [kind for _, kind in run(envelope, values)]
    assert kinds.count("breach") == 1 and "restored" not in kinds
    later = run(envelope, [(6.0 + t / 10, 8.5) for t in range(15)])
    assert later == [(6.0 + RESTORE_S, "restored")]


def test_recovery_is_repeated_when_the_value_crosses_again_or_gets_no_better():
    envelope = Envelope(Limits(max_altitude_m=10))
    assert run(envelope, [(0.0, 11.0)]) == [(0.0, "breach")]
    # Getting better (by more than a quarter of the 2 m margin): no repeat.
    assert run(envelope, [(0.5, 10.8), (REPEAT_S + 0.1, 10.3)]) == []
    # No better than at the last recovery a while after it: again, and again.
    assert run(envelope, [(REPEAT_S + 0.2, 10.6), (REPEAT_S * 2 + 0.2, 10.7)]) == [
        (REPEAT_S + 0.2, "again"),
        (REPEAT_S * 2 + 0.2, "again"),
    ]
    # Back under the limit, then across it again: again at once (not closer together
    # than MIN_REPEAT_S).
    t = REPEAT_S * 2 + 0.2
    steps = run(envelope, [(t + 0.1, 9.9), (t + MIN_REPEAT_S + 0.05, 10.2)])
    assert steps == [(t + MIN_REPEAT_S + 0.05, "again")]


def test_geofence_and_speed_are_watched_and_unknown_values_are_not():
    limits = Limits(geofence_center=CENTRE, geofence_radius_m=20, max_speed_mps=2)
    envelope = Envelope(limits)
    assert envelope.update(at(north=None, speed=None), 0.0) == []
    steps = envelope.update(at(north=25.0, speed=3.0), 0.1)
    assert sorted(step.breach.limit for step in steps) == ["geofence", "speed"]
    fence = next(step.breach for step in steps if step.breach.limit == "geofence")
    assert fence.value == pytest.approx(25.0, abs=0.01) and fence.target == 16.0
    assert fence.centre == CENTRE
    assert Envelope(Limits()).tracks == {}


class FakeVehicle:
    def __init__(self) -> None:
        self.alt = 5.0
        self.recovered: list[Breach] = []
        self.fail = False

    def state(self) -> VehicleState:
        return at(self.alt)

    async def recover(self, breach: Breach) -> str:
        self.recovered.append(breach)
        if self.fail:
            raise RuntimeError("autopilot said no")
        return "descend"


async def wait_for(predicate: Any, within: float = 5.0) -> None:
    deadline = time.monotonic() + within
    while True:
        if predicate():
            return
        assert time.monotonic() < deadline, f"timed out waiting for {predicate}"
        await asyncio.sleep(0.01)


async def test_the_watch_recovers_reports_once_and_reports_the_return():
    vehicle = FakeVehicle()
    told: list[tuple[str, dict[str, Any]]] = []

    async def notify(event: str, data: dict[str, Any]) -> None:
        told.append((event, data))

    watch = EnvelopeWatch(
        limits=Limits(max_altitude_m=10),
        state=vehicle.state,
        recover=vehicle.recover,
        notify=notify,
        period_s=0.01,
    )
    async with watch:
        vehicle.alt = 12.0
        await wait_for(lambda: told)
        assert told == [
            (
                "envelope_breach",
                {"limit": "altitude", "value": 12.0, "limit_value": 10.0, "action": "descend"},
            )
        ]
        await wait_for(lambda: len(vehicle.recovered) >= 2)  # no better: again
        assert len(told) == 1  # ... but reported once
        vehicle.alt = 8.0
        await wait_for(lambda: len(told) == 2)
        event, data = told[1]
        assert event == "envelope_restored" and data["value"] == 8.0
        assert data["duration_ms"] >= RESTORE_S * 1000
        vehicle.fail = True
        vehicle.alt = 12.0
        await wait_for(lambda: len(told) == 3)
        assert told[2][1]["action"] == "recovery failed: autopilot said no"
    await watch.stop()  # idempotent
    assert watch.breaches == 2


def test_a_task_without_limits_is_not_watched():
    async def never(*_: Any) -> Any:
        raise AssertionError("not called")

    watch = EnvelopeWatch(limits=Limits(), state=VehicleState, recover=never, notify=never)
    assert not watch.watching
