"""The Raspberry Pi car adapter, on gpiozero mock pins wired to the kinematic world.

Every car runs on its simulator (the integration's hook, through agents.simulation).
Kinematics tests step the world by hand (the simulator's ``hz: 0``) so distances are
exact; the obstacle watch and the distance sensor run in real time, as they do on the
car.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import gpiozero
import pytest

from agents.geo import distance_m, local_offset_m
from agents.protocol import Limits
from agents.safety import CommandGate, Refusal
from agents.simulation import adapter_simulated, simulator_running
from agents.vehicles.base import AdapterError
from agents.vehicles.car.adapter import TELEMETRY_TOPICS, CarAdapter
from agents.vehicles.car.kinematics import Pose
from agents.vehicles.car.sim.world import Box, CarWorld, Circle
from agents.vehicles.registry import adapter_create

MakeCar = Callable[..., Awaitable[CarAdapter]]

FULL = 0.5  # max_speed_mps used below: ground speed at full power


#: make_car's keywords that are the simulator's parameters (``hz`` as ``sim_hz``).
SIMULATOR = {
    "sim_hz": "hz",
    "battery_pct": "battery_pct",
    "battery_drain_pct_per_s": "battery_drain_pct_per_s",
    "body_radius_m": "body_radius_m",
    "obstacles": "obstacles",
}


@pytest.fixture
async def make_car() -> AsyncIterator[MakeCar]:
    """Start simulated cars; every one (and its simulator) is closed after the test."""
    async with contextlib.AsyncExitStack() as stack:

        async def make(**options: Any) -> CarAdapter:
            simulator = {
                SIMULATOR[key]: options.pop(key) for key in list(options) if key in SIMULATOR
            }
            car, _ = await stack.enter_async_context(
                adapter_simulated("car", {"max_speed_mps": FULL, **options, "simulator": simulator})
            )
            assert isinstance(car, CarAdapter)
            return car

        yield make


def world_of(car: CarAdapter) -> CarWorld:
    """The simulated world: the simulator hands it to the car as its sensors."""
    assert isinstance(car.sensors, CarWorld)
    return car.sensors


def run_world(world: CarWorld, seconds: float, dt: float = 0.01) -> None:
    for _ in range(round(seconds / dt)):
        world.step(dt)


async def wait_until(predicate: Callable[[], bool], within: float = 2.0) -> None:
    deadline = time.monotonic() + within
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.005)


# --------------------------------------------------------------------------------------
# Driving
# --------------------------------------------------------------------------------------


async def test_forward_moves_along_the_heading_by_the_motor_values(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, heading_deg=90)  # facing east
    world = world_of(car)

    await car.execute("forward", {"speed": 1.0})
    world.step(0.01)
    # What moved the world is what gpiozero put on the motor driver's pins.
    assert world.efforts == tuple(car.robot.value) == (1.0, 1.0)
    run_world(world, 0.99)

    pose = world.pose
    assert pose.east_m == pytest.approx(FULL * 1.0, abs=1e-6)
    assert pose.north_m == pytest.approx(0.0, abs=1e-6)
    assert pose.heading_deg == pytest.approx(90.0)
    north, east = local_offset_m(world.origin, world.position)
    assert (north, east) == (pytest.approx(0.0, abs=1e-3), pytest.approx(0.5, abs=1e-3))
    assert car.state().speed_mps == pytest.approx(FULL)


async def test_backward_moves_against_the_heading(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0)
    await car.execute("backward", {"speed": 1.0})
    run_world(world_of(car), 1.0)
    assert world_of(car).pose.north_m == pytest.approx(-FULL, abs=1e-6)


@pytest.mark.parametrize(("command", "sign"), [("left", -1), ("right", 1)])
async def test_left_and_right_turn_on_the_spot(make_car: MakeCar, command: str, sign: int) -> None:
    car = await make_car(sim_hz=0, heading_deg=180, track_width_m=0.15)
    await car.execute(command, {"speed": 0.2})
    run_world(world_of(car), 0.5)

    # Wheels at +-0.2 * 0.5 m/s on a 0.15 m track: 2 * 0.1 / 0.15 rad/s for 0.5 s.
    turned = math.degrees(2 * 0.2 * FULL / 0.15 * 0.5)
    pose = world_of(car).pose
    assert pose.heading_deg == pytest.approx(180 + sign * turned, abs=1e-6)
    assert math.hypot(pose.north_m, pose.east_m) == pytest.approx(0.0, abs=1e-9)


async def test_stop_stops(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0)
    world = world_of(car)
    await car.execute("forward", {"speed": 0.8})
    run_world(world, 0.5)
    await car.execute("stop", {})
    world.step(0.01)
    before = world.pose
    run_world(world, 1.0)

    assert world.pose == before
    assert world.speed_mps == 0.0
    assert car.telemetry()["motors"] == {"left": 0.0, "right": 0.0}


async def test_speed_scales_the_distance_travelled(make_car: MakeCar) -> None:
    slow = await make_car(sim_hz=0)
    fast = await make_car(sim_hz=0)
    await slow.execute("forward", {"speed": 0.25})
    await fast.execute("forward", {"speed": 1.0})
    run_world(world_of(slow), 1.0)
    run_world(world_of(fast), 1.0)

    assert world_of(slow).pose.north_m == pytest.approx(0.25 * FULL)
    assert world_of(fast).pose.north_m == pytest.approx(4 * world_of(slow).pose.north_m)


async def test_the_world_runs_by_itself_once_started(make_car: MakeCar) -> None:
    car = await make_car()  # default: the world steps at 50 Hz on the event loop
    await car.execute("forward", {"speed": 1.0})
    await asyncio.sleep(0.4)
    await car.execute("stop", {})
    await asyncio.sleep(0.05)
    assert world_of(car).pose.north_m == pytest.approx(0.4 * FULL, abs=0.05)


async def test_phase_enable_driver_drives_the_same(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, motor_driver="phase_enable")
    await car.execute("backward", {"speed": 0.5})
    run_world(world_of(car), 1.0)
    assert world_of(car).pose.north_m == pytest.approx(-0.5 * FULL)


async def test_battery_drains_with_motor_effort_only(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, battery_drain_pct_per_s=0.1)
    world = world_of(car)
    run_world(world, 10.0)
    assert car.telemetry()["battery_level"] == 100.0
    await car.execute("forward", {"speed": 0.5})
    run_world(world, 10.0)
    assert car.state().battery == pytest.approx(100.0 - 0.1 * 0.5 * 10)


async def test_an_empty_battery_stops_the_wheels(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, battery_pct=0)
    await car.execute("forward", {"speed": 1.0})
    run_world(world_of(car), 1.0)
    assert world_of(car).pose.north_m == 0.0


async def test_the_car_cannot_drive_through_an_obstacle(make_car: MakeCar) -> None:
    # No distance sensor: nothing stops the car but the wall itself.
    car = await make_car(sim_hz=0, body_radius_m=0.1)
    world = world_of(car)
    world.add_obstacle(Box(north=1.0, east=0.0, size_north=0.2, size_east=2.0))
    await car.execute("forward", {"speed": 1.0})
    run_world(world, 5.0)

    assert world.pose.north_m == pytest.approx(0.9 - 0.1, abs=1e-3)  # touching
    assert world.collisions == 1
    assert world.in_contact
    await car.execute("backward", {"speed": 1.0})
    run_world(world, 0.5)
    assert world.pose.north_m < 0.6
    assert not world.in_contact


# --------------------------------------------------------------------------------------
# Camera arm
# --------------------------------------------------------------------------------------


async def test_camera_commands_move_the_servos_and_clamp(make_car: MakeCar) -> None:
    car = await make_car(camera_arm=True)
    await car.execute("camera_up", {"step_deg": 10})
    await car.execute("camera_up", {"step_deg": 10})
    await car.execute("camera_right", {"step_deg": 45})
    assert (car.telemetry()["camera_tilt"], car.telemetry()["camera_pan"]) == (20.0, 45.0)

    for _ in range(3):
        await car.execute("camera_left", {"step_deg": 90})
        await car.execute("camera_down", {"step_deg": 90})
    assert (car.telemetry()["camera_pan"], car.telemetry()["camera_tilt"]) == (-90.0, -90.0)
    # At the end stop the pan servo gets its shortest pulse (0.5 ms of a 20 ms frame).
    pan_pin = car.pin_factory.pin(12)
    assert pan_pin.frequency == 50
    assert pan_pin.state * 0.020 == pytest.approx(0.0005)

    await car.execute("camera_center", {})
    assert (car.telemetry()["camera_pan"], car.telemetry()["camera_tilt"]) == (0.0, 0.0)
    assert pan_pin.state * 0.020 == pytest.approx(0.0015)


async def test_a_reversed_servo_keeps_the_direction_convention(make_car: MakeCar) -> None:
    car = await make_car(camera_arm=True, camera_pan_reversed=True)
    await car.execute("camera_right", {"step_deg": 90})
    assert car.telemetry()["camera_pan"] == 90.0
    assert car.pin_factory.pin(12).state * 0.020 == pytest.approx(0.0005)  # other end


async def test_neutral_stops_the_motors_but_leaves_the_camera(make_car: MakeCar) -> None:
    car = await make_car(camera_arm=True)
    await car.execute("camera_left", {"step_deg": 30})
    await car.execute("forward", {})
    await car.neutral()
    assert car.telemetry()["motors"] == {"left": 0.0, "right": 0.0}
    assert car.telemetry()["camera_pan"] == -30.0


# --------------------------------------------------------------------------------------
# Distance sensor and obstacle stop
# --------------------------------------------------------------------------------------


async def test_the_distance_sensor_measures_the_world(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, distance_sensor=True)
    world = world_of(car)
    assert car.sensor.distance == pytest.approx(4.0)  # nothing in range: max reading
    world.place_obstacle_ahead(1.2)
    await wait_until(lambda: car.sensor.distance < 2.0)
    await asyncio.sleep(0.3)
    assert car.sensor.distance == pytest.approx(1.2, abs=0.005)
    assert car.telemetry()["distance_ahead"] == pytest.approx(1.2, abs=0.005)


async def test_an_obstacle_stops_a_moving_car_before_it_hits(
    make_car: MakeCar,
) -> None:
    car = await make_car(distance_sensor=True, watch_hz=25)
    world = world_of(car)
    await car.execute("forward", {"speed": 0.5})
    await asyncio.sleep(0.2)
    assert world.speed_mps > 0

    world.place_obstacle_ahead(0.15)
    seen = stopped = None
    deadline = time.monotonic() + 2.0
    while (seen is None or stopped is None) and time.monotonic() < deadline:
        now = time.monotonic()
        if seen is None and car.sensor.distance < 0.25:
            seen = now
        if stopped is None and tuple(car.robot.value) == (0.0, 0.0):
            stopped = now
        await asyncio.sleep(0.002)
    # Seen, then stopped, and the car never touched it: how soon after it saw it (a
    # watch period, 40 ms) is for a benchmark to measure, not a test on a busy machine.
    assert seen is not None and stopped is not None
    await asyncio.sleep(0.1)
    assert world.speed_mps == 0.0
    assert world.collisions == 0
    assert car.obstacle_stops >= 1

    with pytest.raises(AdapterError) as refused:
        await car.execute("forward", {"speed": 0.3})
    assert refused.value.code == "obstacle"
    assert " cm ahead" in str(refused.value)
    assert tuple(car.robot.value) == (0.0, 0.0)

    # Turning on the spot and backing away stay allowed.
    await car.execute("left", {"speed": 0.2})
    await asyncio.sleep(0.1)
    assert tuple(car.robot.value) == (-0.2, 0.2)
    await car.execute("backward", {"speed": 0.5})
    before = world.pose
    await asyncio.sleep(0.3)
    after = world.pose
    assert math.hypot(after.north_m - before.north_m, after.east_m - before.east_m) > 0.03
    assert tuple(car.robot.value) == (-0.5, -0.5)


async def test_forward_is_allowed_again_once_the_obstacle_is_gone(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, distance_sensor=True)
    post = world_of(car).place_obstacle_ahead(0.1)
    await wait_until(lambda: car.telemetry()["distance_ahead"] < 0.25)
    with pytest.raises(AdapterError):
        await car.execute("forward", {})
    world_of(car).remove_obstacle(post)
    await wait_until(lambda: car.telemetry()["distance_ahead"] > 3.9)
    await car.execute("forward", {})
    assert tuple(car.robot.value) == (0.5, 0.5)


# --------------------------------------------------------------------------------------
# Vocabulary, telemetry, safety hooks
# --------------------------------------------------------------------------------------


async def test_telemetry_has_every_topic(make_car: MakeCar) -> None:
    car = await make_car(camera_arm=True, distance_sensor=True)
    data = car.telemetry()
    assert set(car.telemetry_topics()) == set(data) == set(TELEMETRY_TOPICS)
    assert set(TELEMETRY_TOPICS) == {
        "battery_level",
        "location",
        "heading",
        "speed",
        "distance_ahead",
        "camera_pan",
        "camera_tilt",
        "motors",
    }
    assert all(value is not None for value in data.values()), data
    assert set(data["location"]) == {"lat", "lon"}
    assert set(data["motors"]) == {"left", "right"}

    bare = await make_car()
    assert bare.telemetry()["distance_ahead"] is None
    assert bare.telemetry()["camera_pan"] is None


async def test_state_reports_position_heading_speed_and_battery(make_car: MakeCar) -> None:
    car = await make_car(origin=[38.7, -9.1], heading_deg=45)
    state = car.state()
    assert state.position == pytest.approx((38.7, -9.1))
    assert state.heading_deg == 45.0
    assert state.speed_mps == 0.0
    assert state.battery == 100.0


@pytest.mark.parametrize("action", ["stop", "land", "return_to_home"])
async def test_safe_action_stops_the_car(make_car: MakeCar, action: str) -> None:
    car = await make_car(sim_hz=0)
    await car.execute("forward", {"speed": 1.0})
    run_world(world_of(car), 0.2)
    await car.safe_action(action)
    here = world_of(car).pose
    run_world(world_of(car), 1.0)
    assert world_of(car).pose == here


async def test_vocabulary_without_and_with_the_camera_arm(make_car: MakeCar) -> None:
    plain = {c.name: c for c in (await make_car()).commands()}
    assert set(plain) == {"forward", "backward", "left", "right", "stop"}
    assert {c.group for c in plain.values()} == {"movement"}
    for name, key in [
        ("forward", "ArrowUp"),
        ("backward", "ArrowDown"),
        ("left", "ArrowLeft"),
        ("right", "ArrowRight"),
    ]:
        spec = plain[name]
        assert (spec.key, spec.motion, spec.speed_arg) == (key, True, "speed")
    assert plain["forward"].args["speed"]["default"] == plain["backward"].args["speed"]["default"]
    assert plain["forward"].args["speed"]["default"] == 0.5
    # Turning on the spot defaults to about 45°/s: 0.785 rad/s on a 0.15 m track is
    # 0.059 m/s a wheel, 0.118 of the default car's 0.5 m/s.
    for name in ("left", "right"):
        assert plain[name].args["speed"]["default"] == 0.118
    assert plain["stop"].key == "Space"

    armed = {c.name: c for c in (await make_car(camera_arm=True)).commands()}
    camera = {n for n, c in armed.items() if c.group == "camera"}
    assert camera == {"camera_up", "camera_down", "camera_left", "camera_right", "camera_center"}
    assert [armed[n].key for n in ("camera_up", "camera_down", "camera_left", "camera_right")] == [
        "w",
        "s",
        "a",
        "d",
    ]
    assert armed["camera_up"].args["step_deg"] == {
        "type": "number",
        "min": 1,
        "max": 90,
        "default": 10,
        "unit": "deg",
    }


async def test_the_gate_refuses_camera_commands_on_a_car_without_the_arm(
    make_car: MakeCar,
) -> None:
    car = await make_car()
    gate = CommandGate(car, allowed=tuple(c.name for c in car.commands()), limits=Limits())
    with pytest.raises(Refusal) as refused:
        gate.check("camera_up", {})
    assert refused.value.code == "unknown_command"
    with pytest.raises(Refusal) as refused:
        gate.check("forward", {"speed": 1.5})
    assert refused.value.code == "bad_args"


async def test_project_gives_the_position_one_second_ahead(make_car: MakeCar) -> None:
    car = await make_car(heading_deg=90, max_speed_mps=0.4)
    here = car.state().position
    assert here is not None
    ahead = car.project("forward", {"speed": 0.5})
    behind = car.project("backward", {"speed": 1.0})
    assert ahead is not None and behind is not None
    assert local_offset_m(here, (ahead.lat, ahead.lon)) == (
        pytest.approx(0.0, abs=1e-6),
        pytest.approx(0.2, abs=1e-6),
    )
    assert local_offset_m(here, (behind.lat, behind.lon))[1] == pytest.approx(-0.4, abs=1e-6)
    assert car.project("left", {"speed": 1.0}) is None
    assert car.project("camera_up", {}) is None


async def test_the_geofence_refuses_forward_out_of_it(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, heading_deg=0)
    here = car.state().position
    assert here is not None
    world_of(car).set_pose(Pose(north_m=4.9, east_m=0.0, heading_deg=0.0))
    gate = CommandGate(
        car,
        allowed=("forward", "backward"),
        limits=Limits(geofence_center=here, geofence_radius_m=5),
    )
    with pytest.raises(Refusal) as refused:
        gate.check("forward", {"speed": 1.0})
    assert refused.value.code == "geofence"
    assert gate.check("backward", {"speed": 1.0}).name == "backward"


# --------------------------------------------------------------------------------------
# Several cars, lifecycle, options
# --------------------------------------------------------------------------------------


async def test_two_simulated_cars_do_not_interfere(make_car: MakeCar) -> None:
    # Same pin numbers, same process: each car has its own mock pin factory.
    one = await make_car(sim_hz=0, distance_sensor=True)
    two = await make_car(sim_hz=0, distance_sensor=True)
    await one.execute("forward", {"speed": 1.0})
    await two.execute("right", {"speed": 0.5})
    world_of(one).place_obstacle_ahead(2.0)
    run_world(world_of(one), 1.0)
    run_world(world_of(two), 1.0)

    assert world_of(one).pose.north_m == pytest.approx(FULL)
    assert world_of(one).pose.heading_deg == 0.0
    assert world_of(two).pose.north_m == pytest.approx(0.0, abs=1e-9)
    assert world_of(two).pose.heading_deg > 0
    assert tuple(two.robot.value) == (0.5, -0.5)
    await wait_until(lambda: one.telemetry()["distance_ahead"] < 2.0)
    await asyncio.sleep(0.3)
    assert two.telemetry()["distance_ahead"] == pytest.approx(4.0)


async def test_close_stops_and_releases_the_pins(make_car: MakeCar) -> None:
    car = await make_car(camera_arm=True, distance_sensor=True)
    factory = car.pin_factory
    await car.execute("forward", {})
    await car.close()

    assert car.robot is None and car.sensor is None and car.pan_servo is None
    # Every pin is free again: new devices can claim them.
    for device in (
        gpiozero.Motor(9, 10, pin_factory=factory),
        gpiozero.Motor(7, 8, pin_factory=factory),
        gpiozero.AngularServo(12, pin_factory=factory),
        gpiozero.AngularServo(13, pin_factory=factory),
        gpiozero.DigitalOutputDevice(17, pin_factory=factory),
        gpiozero.DigitalInputDevice(18, pin_factory=factory),
    ):
        device.close()
    assert factory.pin(9).state == 0  # motors left stopped
    with pytest.raises(AdapterError) as refused:
        await car.execute("forward", {})
    assert refused.value.code == "not_ready"
    await car.close()  # twice is fine


async def test_without_gpio_and_simulate_false_start_fails(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("GPIOZERO_PIN_FACTORY", raising=False)
    monkeypatch.setenv("PIGPIO_ADDR", "127.0.0.1")  # no daemon there: fails fast
    car = adapter_create("car", {"pin_factory": "native"})
    with pytest.raises(AdapterError) as refused:
        await car.start()
    assert refused.value.code == "hardware"
    await car.close()


async def test_the_real_code_path_dead_reckons_from_the_origin(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # gpiozero's "mock" pin factory stands in for a real one (no world, no battery).
    monkeypatch.setenv("GPIOZERO_MOCK_PIN_CLASS", "mockpwmpin")
    origin = (41.15, -8.61)
    car = adapter_create("car", {"pin_factory": "mock", "origin": list(origin)})
    async with car:
        assert isinstance(car, CarAdapter)
        assert car.sensors is None
        assert car.telemetry()["battery_level"] is None
        await car.execute("forward", {"speed": 1.0})
        await asyncio.sleep(0.5)
        await car.execute("stop", {})
        position = car.state().position
        assert position is not None
        assert distance_m(origin, position) == pytest.approx(0.25, abs=0.06)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"left_motor_pins": [7, 10]}, "pin 7"),
        ({"camera_arm": True, "camera_pan_pin": 17, "distance_sensor": True}, "pin 17"),
        ({"watch_hz": 10}, "watch_hz"),
        ({"motor_driver": "steam"}, "motor_driver"),
        ({"origin": [91, 0]}, "origin"),
        ({"distance_sensor": "yes"}, "distance_sensor"),
    ],
)
def test_bad_options_are_refused(options: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        adapter_create("car", options)


async def test_obstacles_from_the_options(make_car: MakeCar) -> None:
    car = await make_car(sim_hz=0, obstacles=[{"circle": [0.5, 0, 0.1]}, {"box": [0, 3, 1, 1]}])
    assert world_of(car).obstacles == [Circle(0.5, 0.0, 0.1), Box(0.0, 3.0, 1.0, 1.0)]


def test_unknown_options_are_refused_by_name() -> None:
    # A misspelt distance_sensor must not leave the obstacle stop silently off.
    with pytest.raises(ValueError, match="car options: unknown keys distance_senor, sim_hz"):
        adapter_create("car", {"distance_senor": True, "sim_hz": 0, "vehicle_type": "car"})


async def test_bad_simulator_parameters_are_refused_before_anything_starts() -> None:
    with pytest.raises(ValueError, match=r"car option simulator.obstacles: obstacles\[0\]"):
        async with simulator_running("car", {"simulator": {"obstacles": [{"circle": [1, 2]}]}}):
            pass
    with pytest.raises(ValueError, match="car options simulator: unknown key speed"):
        async with simulator_running("car", {"simulator": {"speed": 2}}):
            pass


def test_simulate_is_refused_with_where_simulators_start() -> None:
    with pytest.raises(ValueError, match="python -m agents sim fleet"):
        adapter_create("car", {"simulate": True})
